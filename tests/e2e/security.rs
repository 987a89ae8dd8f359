//! Who may talk to the device (docs/security.md), end to end with the peers users run:
//! the mbgate binary, pymodbus' ModbusTcpServer as the device behind a TCP line (its
//! registers and coils read directly to see what reached it), raw masters bound to
//! other loopback addresses (127.0.0.2) and over IPv6, pymodbus' AsyncModbusTlsClient
//! and Python's ssl module as Modbus/TCP Security masters, `openssl s_client`, and
//! certificates made with the openssl CLI as the user guide shows.

use crate::common;

use common::pki::Pki;
use common::*;
use std::io::{BufRead, BufReader, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::Path;
use std::process::{Child, ChildStdin, Command, Stdio};
use std::time::Duration;

/// The stopped gateway's counters, from the line it logs at the stop.
fn counters(gw: &mut Proc) -> std::collections::HashMap<String, u64> {
    assert!(gw.terminate(Duration::from_secs(10)).success());
    let log = gw.log();
    let line = log
        .lines()
        .rev()
        .find(|l| l.contains("stopped") && l.contains("connections_denied="))
        .unwrap_or_else(|| panic!("no counters:\n{log}"));
    line.split_whitespace()
        .filter_map(|t| {
            let (k, v) = t.rsplit_once('=')?;
            Some((k.rsplit('=').next()?.to_string(), v.parse().ok()?))
        })
        .collect()
}

/// pymodbus' ModbusTcpServer as the device (unit 1; holding register i = 1000 + i,
/// coil i on when i % 3 == 0), and the `[[line]]` that reaches it.
fn tcp_device() -> (Py, u16, String) {
    let port = free_port();
    let device = Py::start("tcp_device.py", &["--port", &port.to_string()]);
    let line = format!("[[line]]\n[line.tcp]\naddress = \"127.0.0.1:{port}\"\n\n");
    (device, port, line)
}

/// A connection straight to the device, to see what reached it.
fn device(port: u16) -> TcpStream {
    let s = TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    s
}

/// Holding registers `addr..addr + n` as the device has them.
fn registers(port: u16, addr: u16, n: u16) -> Vec<u16> {
    let reply = transact(&mut device(port), &read_req(0x77, 1, addr, n));
    reply[9..]
        .chunks(2)
        .map(|w| u16::from_be_bytes([w[0], w[1]]))
        .collect()
}

/// Coils `addr..addr + n` as the device has them.
fn coils(port: u16, addr: u16, n: u16) -> Vec<bool> {
    let req = mbgate::frame::Adu::build(0x78, 1, &[1, (addr >> 8) as u8, addr as u8, 0, n as u8]);
    let reply = transact(&mut device(port), req.as_bytes());
    (0..n as usize)
        .map(|i| reply[9 + i / 8] & (1 << (i % 8)) != 0)
        .collect()
}

fn connect(addr: SocketAddr) -> TcpStream {
    let s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    s
}

/// A connection to `to` from the loopback address `from` (127.0.0.2, ...).
fn connect_from(from: &str, to: SocketAddr) -> TcpStream {
    use socket2::{Domain, Socket, Type};
    let from: SocketAddr = format!("{from}:0").parse().unwrap();
    let s = Socket::new(Domain::for_address(to), Type::STREAM, None).unwrap();
    s.bind(&from.into()).unwrap();
    s.connect(&to.into()).unwrap();
    let s: TcpStream = s.into();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    s
}

/// A request of `pdu` to unit 1.
fn req(tid: u16, pdu: &[u8]) -> Vec<u8> {
    mbgate::frame::Adu::build(tid, 1, pdu).as_bytes().to_vec()
}

/// The exception reply to `req`'s function with `code`.
fn exception(tid: u16, fc: u8, code: u8) -> Vec<u8> {
    req(tid, &[fc | 0x80, code])
}

/// An allow list takes 127.0.0.1 and refuses 127.0.0.2: the refused connection is
/// closed before its request is read, so the write it sent never reaches the device;
/// the refusal is logged once for three attempts and counted. A dual-stack listener
/// judges an IPv4 master (seen as ::ffff:127.0.0.1) by its IPv4 address, and an IPv6
/// master by its own; a listener without a list says at start that it takes everyone.
#[test]
fn an_allow_list_refuses_other_sources_before_reading_a_byte() {
    let dir = tempdir();
    let (_device, port, line) = tcp_device();
    let text = format!(
        "{line}[[listen]]\naddress = \"127.0.0.1:0\"\nallow = [\"127.0.0.1\", \"10.0.0.0/8\"]\n\n\
         [[listen]]\naddress = \"[::]:0\"\nallow = [\"127.0.0.0/31\", \"::1\"]\n\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\n\n[log]\nlevel = \"debug\"\n"
    );
    let (mut gw, addrs) = gateway_from_file(dir.path(), &text, 3);
    let log = gw.log();
    assert!(
        log.contains("listen[0]: who: only from 127.0.0.1, 10.0.0.0/8, plain TCP"),
        "{log}"
    );
    assert!(
        log.contains("listen[2]: who: from everyone (no allow list), plain TCP"),
        "{log}"
    );

    let mut ok = connect(addrs[0]);
    assert_eq!(
        transact(&mut ok, &read_req(1, 1, 8, 1)),
        read_reply(1, 1, &[1008])
    );
    for _ in 0..3 {
        let mut refused = connect_from("127.0.0.2", addrs[0]);
        // Sent at once: the gateway must not read it, let alone pass it on.
        let _ = refused.write_all(&write_req(2, 1, 8, &[0x1234]));
        assert!(
            is_closed(&mut refused, Duration::from_secs(5)),
            "refused source still connected"
        );
    }
    assert_eq!(
        registers(port, 8, 1),
        [1008],
        "the refused write reached the device"
    );
    gw.wait_log(
        "connection refused: 127.0.0.2 is not in listen[0].allow",
        Duration::from_secs(5),
    );

    // Dual stack: 127.0.0.1 as ::ffff:127.0.0.1 is in 127.0.0.0/31; 127.0.0.2 is not.
    let v6 = addrs[1];
    let mapped = SocketAddr::from(([127, 0, 0, 1], v6.port()));
    assert_eq!(
        transact(&mut connect(mapped), &read_req(3, 1, 9, 1)),
        read_reply(3, 1, &[1009])
    );
    let loop6 = SocketAddr::from((std::net::Ipv6Addr::LOCALHOST, v6.port()));
    assert_eq!(
        transact(&mut connect(loop6), &read_req(4, 1, 9, 1)),
        read_reply(4, 1, &[1009])
    );
    let mut other = connect_from("127.0.0.2", SocketAddr::from(([127, 0, 0, 2], v6.port())));
    let _ = other.write_all(&read_req(5, 1, 9, 1));
    assert!(is_closed(&mut other, Duration::from_secs(5)));
    // The listener open to all takes 127.0.0.2.
    let mut open = connect_from("127.0.0.2", addrs[2]);
    assert_eq!(
        transact(&mut open, &read_req(6, 1, 9, 1)),
        read_reply(6, 1, &[1009])
    );

    let log = gw.log();
    assert_eq!(
        log.matches("is not in listen[0].allow").count(),
        1,
        "three refusals, one line:\n{log}"
    );
    let stats = counters(&mut gw);
    assert_eq!(
        (stats["connections_denied"], stats["requests"]),
        (4, 4),
        "{stats:?}"
    );
}

/// Each write function code (05, 06, 15, 16, 22, 23) and diagnostics (08) from a master
/// of a read-only listener is answered 0x01 at once and never reaches the device,
/// whose coils and registers are unchanged when read directly; reads pass.
#[test]
fn a_read_only_listener_refuses_every_write_and_the_device_is_unchanged() {
    let dir = tempdir();
    let (_device, port, line) = tcp_device();
    let text = format!(
        "{line}[[listen]]\naddress = \"127.0.0.1:0\"\nread_only = true\n\n[log]\nlevel = \"debug\"\n"
    );
    let (mut gw, addrs) = gateway_from_file(dir.path(), &text, 1);
    assert!(
        gw.log().contains("listen[0]: what: read only"),
        "{}",
        gw.log()
    );
    let mut m = connect(addrs[0]);
    let writes: [&[u8]; 7] = [
        &[0x05, 0, 1, 0xFF, 0],                          // coil 1 on
        &[0x06, 0, 8, 0x11, 0x11],                       // register 8
        &[0x0F, 0, 1, 0, 2, 1, 0x03],                    // coils 1, 2 on
        &[0x10, 0, 9, 0, 2, 4, 0x22, 0x22, 0x33, 0x33],  // registers 9, 10
        &[0x16, 0, 11, 0, 0, 0, 0xFF],                   // register 11 = 0x00FF
        &[0x17, 0, 0, 0, 1, 0, 12, 0, 1, 2, 0x44, 0x44], // register 12
        &[0x08, 0, 1, 0, 0],                             // restart communications
    ];
    for (i, pdu) in writes.iter().enumerate() {
        let tid = 10 + i as u16;
        assert_eq!(
            transact(&mut m, &req(tid, pdu)),
            exception(tid, pdu[0], 0x01),
            "FC {:#04x}",
            pdu[0]
        );
    }
    assert_eq!(registers(port, 8, 5), [1008, 1009, 1010, 1011, 1012]);
    assert_eq!(coils(port, 0, 4), [true, false, false, true]);
    assert_eq!(
        transact(&mut m, &read_req(20, 1, 8, 2)),
        read_reply(20, 1, &[1008, 1009])
    );
    assert_eq!(
        transact(&mut m, &req(21, &[1, 0, 0, 0, 4])),
        req(21, &[1, 1, 0b1001])
    );
    gw.wait_log(
        "request refused: the listener is read only; exception 0x01",
        Duration::from_secs(5),
    );
    let stats = counters(&mut gw);
    assert_eq!((stats["denied"], stats["requests"]), (7, 2), "{stats:?}");
}

/// FC 43 (0x2B) with MEI type 14, read device identification, is a read only in its own
/// shape (a read device id code and an object id, Modbus Application Protocol §6.21):
/// with trailing bytes it is answered 0x03 by the gateway and never goes on the line,
/// so a read-only master cannot carry bytes of its own to the device that way.
#[test]
fn a_read_only_master_cannot_put_trailing_bytes_on_the_line_with_fc_43() {
    let dir = tempdir();
    let (_device, _port, line) = tcp_device();
    let text = format!("{line}[[listen]]\naddress = \"127.0.0.1:0\"\nread_only = true\n");
    let (mut gw, addrs) = gateway_from_file(dir.path(), &text, 1);
    let mut m = connect(addrs[0]);
    let mut long = vec![0x2B, 0x0E, 0x01, 0x00];
    long.extend([0xA5; 200]);
    for (tid, pdu) in [
        (1u16, &long[..]),
        (2, &[0x2B, 0x0E, 0x01, 0x00, 0x00][..]),
        (3, &[0x2B, 0x0E, 0x07, 0x00][..]),
        (4, &[0x2B, 0x0E, 0x01][..]),
    ] {
        assert_eq!(
            transact(&mut m, &req(tid, pdu)),
            exception(tid, 0x2B, 0x03),
            "{pdu:02X?}"
        );
    }
    // Its own shape goes to the device, whose answer starts with MEI 14 and the code.
    let reply = transact(&mut m, &req(5, &[0x2B, 0x0E, 0x01, 0x00]));
    assert_eq!(&reply[7..10], &[0x2B, 0x0E, 0x01], "{reply:02X?}");
    let stats = counters(&mut gw);
    assert_eq!(
        (stats["bad_requests"], stats["requests"]),
        (4, 1),
        "{stats:?}"
    );
}

/// `allow = ["::/0"]` on a dual-stack listener takes IPv4 masters too (seen as
/// ::ffff:127.0.0.1), as it takes IPv6 ones: what the one who wrote it meant.
#[test]
fn allow_all_of_ipv6_on_a_dual_stack_listener_takes_ipv4_masters() {
    let dir = tempdir();
    let (_device, _port, line) = tcp_device();
    let text = format!("{line}[[listen]]\naddress = \"[::]:0\"\nallow = [\"::/0\"]\n");
    let (mut gw, addrs) = gateway_from_file(dir.path(), &text, 1);
    let port = addrs[0].port();
    for (tid, to) in [
        (1u16, SocketAddr::from(([127, 0, 0, 1], port))),
        (2, SocketAddr::from(([127, 0, 0, 2], port))),
        (3, SocketAddr::from((std::net::Ipv6Addr::LOCALHOST, port))),
    ] {
        assert_eq!(
            transact(&mut connect(to), &read_req(tid, 1, 8, 1)),
            read_reply(tid, 1, &[1008]),
            "{to}"
        );
    }
    let stats = counters(&mut gw);
    assert_eq!(stats["connections_denied"], 0, "{stats:?}");
}

/// Write rules: unit 1, FC 06 and 16, registers 8 and 9 only. A write inside passes and
/// changes the device; one that leaves the range, uses another function or another
/// unit is answered 0x01 and the device keeps its value.
#[test]
fn write_rules_permit_only_their_units_functions_and_addresses() {
    let dir = tempdir();
    let (_device, port, line) = tcp_device();
    let text = format!(
        "{line}[[listen]]\naddress = \"127.0.0.1:0\"\n\
         write = [{{ units = [1], functions = [6, 16], addresses = \"8-9\" }}]\n\n\
         [log]\nlevel = \"debug\"\n"
    );
    let (mut gw, addrs) = gateway_from_file(dir.path(), &text, 1);
    let mut m = connect(addrs[0]);
    assert_eq!(
        transact(&mut m, &req(1, &[6, 0, 8, 0, 0x11])),
        req(1, &[6, 0, 8, 0, 0x11])
    );
    assert_eq!(
        transact(&mut m, &req(2, &[6, 0, 10, 0, 0x22])),
        exception(2, 6, 1)
    );
    assert_eq!(
        transact(&mut m, &write_req(3, 1, 8, &[0x33, 0x44])),
        req(3, &[0x10, 0, 8, 0, 2])
    );
    assert_eq!(
        transact(&mut m, &write_req(4, 1, 9, &[0x55, 0x66])),
        exception(4, 0x10, 1)
    );
    assert_eq!(
        transact(&mut m, &req(5, &[5, 0, 8, 0xFF, 0])),
        exception(5, 5, 1)
    );
    let other_unit = mbgate::frame::Adu::build(6, 2, &[6, 0, 8, 0, 0x77]);
    assert_eq!(
        transact(&mut m, other_unit.as_bytes()),
        mbgate::frame::Adu::build(6, 2, &[0x86, 1]).as_bytes()
    );
    assert_eq!(registers(port, 8, 3), [0x33, 0x44, 1010]);
    assert_eq!(coils(port, 8, 1), [false]);
    gw.wait_log(
        "no write rule of the listener permits it",
        Duration::from_secs(5),
    );
    let stats = counters(&mut gw);
    assert_eq!(stats["denied"], 4, "{stats:?}");
}

// ---------------------------------------------------------------------------------
// Modbus/TCP Security

/// tests/py/tls_master.py: a TLS master driven one command at a time.
struct TlsMaster {
    child: Child,
    stdin: ChildStdin,
    out: BufReader<std::process::ChildStdout>,
}

impl TlsMaster {
    fn start(port: u16, pki: &Pki, cert: Option<&str>) -> TlsMaster {
        let mut args = vec![
            repo().join("tests/py/tls_master.py").display().to_string(),
            "--port".into(),
            port.to_string(),
            "--ca".into(),
            pki.pem("ca"),
        ];
        if let Some(c) = cert {
            args.extend(["--cert".into(), pki.pem(c), "--key".into(), pki.key(c)]);
        }
        let mut child = Command::new(python())
            .args(&args)
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
        TlsMaster { child, stdin, out }
    }

    fn ask(&mut self, cmd: &str) -> serde_json::Value {
        writeln!(self.stdin, "{cmd}").unwrap();
        let mut line = String::new();
        self.out.read_line(&mut line).unwrap();
        eprintln!("tls_master {cmd}: {}", line.trim());
        serde_json::from_str(&line).unwrap_or_else(|_| panic!("{cmd}: {line:?}"))
    }
}

impl Drop for TlsMaster {
    fn drop(&mut self) {
        let _ = writeln!(self.stdin, "quit");
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The certificates of the TLS tests: the gateway's, and masters with roles operator,
/// viewer and admin (no [[role]] names it), without a role, from another CA, expired.
fn pki(dir: &Path) -> Pki {
    let pki = Pki::new(&dir.join("pki"));
    pki.master("operator-1", "ca", Some("operator"), 30);
    pki.master("viewer-1", "ca", Some("viewer"), 30);
    pki.master("admin-1", "ca", Some("admin"), 30);
    pki.master("nobody", "ca", None, 30);
    pki.master("expired", "ca", Some("operator"), -1);
    pki.ca("other");
    pki.master("stranger", "other", Some("operator"), 30);
    pki
}

const ROLES: &str =
    "[[role]]\nname = \"operator\"\n\n[[role]]\nname = \"viewer\"\nread_only = true\n\n";

/// pymodbus' TLS client: role operator writes (the device changes), role viewer reads
/// but its write is answered 0x01 (the device keeps its value). `mbgate status` and
/// /status.json show each connected master's role and certificate subject.
#[test]
fn the_role_in_the_certificate_decides_what_a_tls_master_may_do() {
    let dir = tempdir();
    let pki = pki(dir.path());
    let (_device, port, line) = tcp_device();
    let metrics = free_port();
    let text = format!(
        "{line}[[listen]]\naddress = \"127.0.0.1:0\"\n{}\n\n{ROLES}\
         [metrics]\nlisten = \"127.0.0.1:{metrics}\"\n\n[log]\nlevel = \"debug\"\n",
        pki.listen_tls("")
    );
    let (mut gw, addrs) = gateway_from_file(dir.path(), &text, 1);
    let tls = addrs[0].port();
    let mut operator = TlsMaster::start(tls, &pki, Some("operator-1"));
    assert_eq!(operator.ask("connect")["ok"], true);
    assert_eq!(
        operator.ask("read 8 2")["registers"],
        serde_json::json!([1008, 1009])
    );
    assert_eq!(operator.ask("write 8 17")["ok"], true);
    let mut viewer = TlsMaster::start(tls, &pki, Some("viewer-1"));
    assert_eq!(viewer.ask("connect")["ok"], true);
    assert_eq!(viewer.ask("read 8 1")["registers"], serde_json::json!([17]));
    assert_eq!(viewer.ask("write 9 18")["exception"], 1);
    assert_eq!(registers(port, 8, 2), [17, 1009]);
    // The log is read by another thread: waited for, not taken at once.
    gw.wait_log(
        "request refused: role \"viewer\" is read only",
        Duration::from_secs(5),
    );
    let log = gw.log();
    assert!(
        log.contains("master connected over TLS")
            && log.contains("role=operator subject=CN=operator-1"),
        "{log}"
    );

    let status = mbgate(&["status", "--metrics", &format!("127.0.0.1:{metrics}")]);
    let roles: Vec<&str> = status
        .stdout
        .lines()
        .filter(|l| l.contains("  master "))
        .collect();
    assert_eq!(roles.len(), 2, "{}", status.stdout);
    assert!(
        roles[0].contains("role operator, CN=operator-1"),
        "{}",
        status.stdout
    );
    assert!(
        roles[1].contains("role viewer, CN=viewer-1"),
        "{}",
        status.stdout
    );
    let json = http_get(metrics, "/status.json");
    assert!(
        json.contains("\"role\":\"viewer\",\"subject\":\"CN=viewer-1\""),
        "{json}"
    );
    drop((operator, viewer));
    let stats = counters(&mut gw);
    assert_eq!(
        (stats["denied"], stats["tls_failed"], stats["tls_refused"]),
        (1, 0, 0)
    );
}

fn http_get(port: u16, path: &str) -> String {
    use std::io::Read;
    let mut s = TcpStream::connect(("127.0.0.1", port)).unwrap();
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut all = String::new();
    s.read_to_string(&mut all).unwrap();
    all
}

/// `openssl s_client` with `args` against `port`, stdin closed; its output.
fn s_client(port: u16, args: &[&str]) -> String {
    let out = Command::new("openssl")
        .args([
            "s_client",
            "-connect",
            &format!("127.0.0.1:{port}"),
            "-servername",
            "localhost",
        ])
        .args(args)
        .stdin(Stdio::null())
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    eprintln!("$ openssl s_client {args:?}\n{text}");
    text
}

/// What a Modbus/TCP Security listener refuses, against Python's ssl module and
/// `openssl s_client`: no client certificate, one from another CA, an expired one,
/// one without a role (no default_role), one whose role no [[role]] names, TLS 1.1.
/// A good certificate completes the handshake over TLS 1.3 and TLS 1.2. Each refusal
/// is logged with its reason and counted; none reaches the device.
#[test]
fn bad_certificates_and_old_protocols_are_refused() {
    let dir = tempdir();
    let pki = pki(dir.path());
    let (_device, port, line) = tcp_device();
    let text = format!(
        "{line}[[listen]]\naddress = \"127.0.0.1:0\"\n{}\n\n{ROLES}[log]\nlevel = \"debug\"\n",
        pki.listen_tls("")
    );
    let (mut gw, addrs) = gateway_from_file(dir.path(), &text, 1);
    let tls = addrs[0].port();
    let good = TlsMaster::start(tls, &pki, Some("operator-1")).ask("handshake");
    assert_eq!(
        (good["ok"].as_bool(), good["protocol"].as_str()),
        (Some(true), Some("TLSv1.3")),
        "{good}"
    );
    assert_eq!(good["subject"], "localhost");
    for (cert, reason) in [
        (None, "peer sent no certificates"),
        (Some("stranger"), "UnknownIssuer"),
        (Some("expired"), "Expired"),
        (
            Some("nobody"),
            "carries no Modbus role and the listener has no default_role",
        ),
        (
            Some("admin-1"),
            "carries the role \"admin\", which no [[role]] names",
        ),
    ] {
        let got = TlsMaster::start(tls, &pki, cert).ask("handshake");
        assert_eq!(got["ok"], false, "{cert:?} was let in: {got}");
        gw.wait_log(reason, Duration::from_secs(5));
    }
    let ok13 = s_client(
        tls,
        &[
            "-cert",
            &pki.pem("operator-1"),
            "-key",
            &pki.key("operator-1"),
            "-CAfile",
            &pki.pem("ca"),
        ],
    );
    assert!(
        ok13.contains("Verify return code: 0 (ok)") && ok13.contains("TLSv1.3"),
        "{ok13}"
    );
    let ok12 = s_client(
        tls,
        &[
            "-tls1_2",
            "-cert",
            &pki.pem("operator-1"),
            "-key",
            &pki.key("operator-1"),
            "-CAfile",
            &pki.pem("ca"),
        ],
    );
    assert!(
        ok12.contains("Protocol  : TLSv1.2") && ok12.contains("Verify return code: 0 (ok)"),
        "{ok12}"
    );
    let no_cert = s_client(tls, &["-tls1_2", "-CAfile", &pki.pem("ca")]);
    assert!(
        !no_cert.contains("Verify return code: 0 (ok)") || no_cert.contains("alert"),
        "{no_cert}"
    );
    // TLS 1.1: OpenSSL 3 would not even offer it at its default security level.
    let old = s_client(
        tls,
        &[
            "-tls1_1",
            "-cipher",
            "DEFAULT:@SECLEVEL=0",
            "-cert",
            &pki.pem("operator-1"),
            "-key",
            &pki.key("operator-1"),
        ],
    );
    // s_client names the protocol it tried even when nothing was agreed.
    assert!(
        old.contains("Cipher is (NONE)") && old.contains("alert handshake failure"),
        "{old}"
    );
    gw.wait_log(
        "TLS handshake failed: peer is incompatible",
        Duration::from_secs(5),
    );
    assert_eq!(registers(port, 0, 1), [0x00FF]);
    let stats = counters(&mut gw);
    assert_eq!(stats["tls_refused"], 2, "{stats:?}");
    assert!(stats["tls_failed"] >= 5, "{stats:?}");
    assert_eq!(
        stats["requests"], 1,
        "the good handshake's read only: {stats:?}"
    );
}

/// TLS on an RTU-over-TCP listener: the RTU frame (unit, PDU, CRC) inside the TLS
/// session, answered with the device's register.
#[test]
fn an_rtu_over_tcp_listener_speaks_tls_too() {
    let dir = tempdir();
    let pki = pki(dir.path());
    let (_device, _port, line) = tcp_device();
    let text = format!(
        "{line}[[listen]]\naddress = \"127.0.0.1:0\"\nframing = \"rtu\"\n{}\n\n{ROLES}\
         [log]\nlevel = \"debug\"\n",
        pki.listen_tls("")
    );
    let (mut gw, addrs) = gateway_from_file(dir.path(), &text, 1);
    let got = TlsMaster::start(addrs[0].port(), &pki, Some("viewer-1")).ask("rtu-read");
    let want = mbgate::frame::rtu::encode(1, &[3, 2, 0, 0xFF]);
    assert_eq!(
        got["reply"].as_str(),
        Some(hexs(&want).replace(' ', "").to_lowercase().as_str()),
        "{got}"
    );
    assert!(gw.terminate(Duration::from_secs(10)).success());
}

/// A certificate without a role gets the listener's default_role (viewer here: reads,
/// no writes).
#[test]
fn a_certificate_without_a_role_gets_the_default_role() {
    let dir = tempdir();
    let pki = pki(dir.path());
    let (_device, port, line) = tcp_device();
    let text = format!(
        "{line}[[listen]]\naddress = \"127.0.0.1:0\"\n{}\n\n{ROLES}[log]\nlevel = \"debug\"\n",
        pki.listen_tls(", default_role = \"viewer\"")
    );
    let (mut gw, addrs) = gateway_from_file(dir.path(), &text, 1);
    let mut m = TlsMaster::start(addrs[0].port(), &pki, Some("nobody"));
    assert_eq!(m.ask("connect")["ok"], true);
    assert_eq!(m.ask("read 8 1")["registers"], serde_json::json!([1008]));
    assert_eq!(m.ask("write 8 1")["exception"], 1);
    assert_eq!(registers(port, 8, 1), [1008]);
    assert!(
        gw.log()
            .contains("no role in its certificate: the default role"),
        "{}",
        gw.log()
    );
    drop(m);
    let _ = counters(&mut gw);
}

/// A master that connects and never starts its handshake does not delay another: the
/// other is served while the first still waits (its connection still open), and the
/// first is closed once `handshake_timeout_ms` has passed. A new gateway certificate
/// read on SIGHUP is presented to new connections, while the master connected before
/// keeps its session and is served on; `mbgate reload` reads it again too, and says so.
#[test]
fn a_stalled_handshake_delays_nobody_and_a_certificate_reload_keeps_masters() {
    let dir = tempdir();
    let pki = pki(dir.path());
    let (_device, _port, line) = tcp_device();
    let socket = dir.path().join("control.sock");
    let text = format!(
        "{line}[[listen]]\naddress = \"127.0.0.1:0\"\n{}\n\n{ROLES}[log]\nlevel = \"debug\"\n\n\
         [control]\nsocket = {:?}\n",
        pki.listen_tls(", handshake_timeout_ms = 5000"),
        socket.display().to_string()
    );
    let (mut gw, addrs) = gateway_from_file(dir.path(), &text, 1);
    let tls = addrs[0].port();
    let mut m = TlsMaster::start(tls, &pki, Some("operator-1"));
    assert_eq!(m.ask("stall")["ok"], true);
    assert_eq!(m.ask("connect")["ok"], true);
    assert_eq!(m.ask("read 0 1")["registers"], serde_json::json!([255]));
    assert_eq!(
        m.ask("stalled")["open"],
        true,
        "served only after the stalled handshake ended"
    );

    // A new certificate for the gateway (another subject), read on SIGHUP.
    pki.sign(
        "gateway",
        "ca",
        "/CN=localhost-renewed",
        "subjectAltName=IP:127.0.0.1,DNS:localhost\n",
        30,
    );
    gw.signal("HUP");
    gw.wait_log(
        "certificate, key and client CA read again",
        Duration::from_secs(5),
    );
    assert_eq!(
        m.ask("read 1 1")["registers"],
        serde_json::json!([1001]),
        "the connected master lost its session"
    );
    let fresh = m.ask("handshake");
    assert_eq!(fresh["subject"], "localhost-renewed", "{fresh}");
    // Once more, through `mbgate reload`: its answer names the listener.
    pki.sign(
        "gateway",
        "ca",
        "/CN=localhost-again",
        "subjectAltName=IP:127.0.0.1,DNS:localhost\n",
        30,
    );
    let run = common::mbgate(&["reload", "--socket", socket.to_str().unwrap()]);
    assert_eq!(run.code, 0, "{}{}", run.stdout, run.stderr);
    assert!(
        run.stdout.contains(
            "listen[0].tls: certificate, key and client CA read again (the gateway is \"CN=localhost-again\")"
        ),
        "{}",
        run.stdout
    );
    let fresh = m.ask("handshake");
    assert_eq!(fresh["subject"], "localhost-again", "{fresh}");
    gw.wait_log("no TLS handshake within 5000 ms", Duration::from_secs(10));
    assert_eq!(m.ask("stalled")["open"], false);
    assert_eq!(m.ask("read 2 1")["registers"], serde_json::json!([1002]));
    drop(m);
    let stats = counters(&mut gw);
    assert_eq!(stats["tls_failed"], 1, "{stats:?}");
}

/// Silent TCP connections to `to`, from `sources` in turn, `n` in all: what an attacker
/// who never starts a handshake holds open. Connects that fail (the backlog full) are
/// not counted.
fn half_open(sources: &[String], to: SocketAddr, n: usize) -> Vec<TcpStream> {
    (0..n)
        .filter_map(|i| {
            let from: SocketAddr = format!("{}:0", sources[i % sources.len()]).parse().unwrap();
            let s =
                socket2::Socket::new(socket2::Domain::IPV4, socket2::Type::STREAM, None).ok()?;
            s.bind(&from.into()).ok()?;
            s.connect_timeout(&to.into(), Duration::from_secs(2)).ok()?;
            Some(s.into())
        })
        .collect()
}

/// A certificate holder's handshakes (pymodbus' TLS master's raw ssl socket: the
/// handshake, then one FC 03 read answered): how many of `n` were served, and their
/// times in ms.
fn handshakes_served(m: &mut TlsMaster, n: usize) -> (usize, Vec<f64>) {
    let mut ms = Vec::new();
    let mut served = 0;
    for _ in 0..n {
        let got = m.ask("handshake");
        if got["ok"] == true && got["reply"].as_str().is_some_and(|r| r.len() > 14) {
            served += 1;
        }
        ms.push(got["ms"].as_f64().unwrap_or(f64::NAN));
    }
    (served, ms)
}

/// Unauthenticated peers cannot lock certificate holders out of a TLS listener
/// (docs/security.md "Handshakes"): with the defaults (32 connection slots, 10 s to
/// finish a handshake, so 128 handshakes in progress, 16 from one source), an attacker
/// holds 400 silent TCP connections from one address, then 400 from 100 addresses,
/// then keeps opening new ones from 100 addresses as fast as it can; meanwhile every
/// handshake of a master with a valid operator certificate (pymodbus' TLS master, then
/// `openssl s_client`) is served. Handshakes that gave way are counted as failed and
/// their log lines capped, as are those of 30 peers that speak HTTP to it (one line).
/// `-- --nocapture` prints the figures docs/security.md quotes.
#[test]
fn unauthenticated_peers_cannot_lock_certificate_holders_out() {
    let dir = tempdir();
    let pki = pki(dir.path());
    let (_device, _port, line) = tcp_device();
    let text = format!(
        "{line}[[listen]]\naddress = \"127.0.0.1:0\"\n{}\n\n{ROLES}",
        pki.listen_tls("")
    );
    let (mut gw, addrs) = gateway_from_file(dir.path(), &text, 1);
    let to = addrs[0];
    let mut m = TlsMaster::start(to.port(), &pki, Some("operator-1"));
    let one = vec!["127.0.0.2".to_string()];
    let many: Vec<String> = (10..110).map(|i| format!("127.0.0.{i}")).collect();

    // 30 peers that speak HTTP to it: 30 failed handshakes, one line in the log.
    for _ in 0..30 {
        let mut s = connect(to);
        let _ = s.write_all(b"GET / HTTP/1.0\r\n\r\n");
        // An alert, then the close.
        let mut alert = Vec::new();
        let end = std::io::Read::read_to_end(&mut s, &mut alert);
        assert!(
            end.is_ok() || end.is_err_and(|e| e.kind() == std::io::ErrorKind::ConnectionReset),
            "still open"
        );
    }
    gw.wait_log("TLS handshake failed", Duration::from_secs(5));
    assert_eq!(
        gw.log().matches("TLS handshake failed").count(),
        1,
        "{}",
        gw.log()
    );

    let held = half_open(&one, to, 400);
    assert!(held.len() >= 100, "only {} connects", held.len());
    std::thread::sleep(Duration::from_millis(300));
    let (served, ms) = handshakes_served(&mut m, 10);
    eprintln!(
        "one source, {} silent connections: {served}/10 served, ms {ms:?}",
        held.len()
    );
    assert_eq!(served, 10, "one source: {ms:?}");
    drop(held);

    let held = half_open(&many, to, 400);
    assert!(held.len() >= 100, "only {} connects", held.len());
    std::thread::sleep(Duration::from_millis(300));
    let (served, ms) = handshakes_served(&mut m, 10);
    eprintln!(
        "100 sources, {} silent connections: {served}/10 served, ms {ms:?}",
        held.len()
    );
    assert_eq!(served, 10, "many sources: {ms:?}");
    drop(held);

    // Churn: new silent connections from 100 sources as fast as one thread opens them
    // (at most 20 000, keeping the newest 400), while the master connects.
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    // `MBGATE_ATTACKERS=N`: N such threads (1 by default), each its 20 000 and 400.
    let threads: usize = std::env::var("MBGATE_ATTACKERS")
        .ok()
        .and_then(|n| n.parse().ok())
        .unwrap_or(1);
    let attackers: Vec<_> = (0..threads)
        .map(|t| {
            let (stop, many) = (stop.clone(), many.clone());
            std::thread::spawn(move || {
                let started = std::time::Instant::now();
                let mut open = std::collections::VecDeque::new();
                let mut opened = 0usize;
                while !stop.load(std::sync::atomic::Ordering::Relaxed) && opened < 20_000 {
                    let from = (opened + 7 * t) % 100;
                    for s in half_open(&many[from..from + 1], to, 1) {
                        open.push_back(s);
                    }
                    opened += 1;
                    if open.len() > 400 {
                        open.pop_front();
                    }
                }
                (opened, started.elapsed())
            })
        })
        .collect();
    std::thread::sleep(Duration::from_millis(300));
    let (served, ms) = handshakes_served(&mut m, 10);
    let ok = s_client(
        to.port(),
        &[
            "-cert",
            &pki.pem("operator-1"),
            "-key",
            &pki.key("operator-1"),
            "-CAfile",
            &pki.pem("ca"),
        ],
    );
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let (mut opened, mut took) = (0, Duration::ZERO);
    for a in attackers {
        let (n, t) = a.join().unwrap();
        opened += n;
        took = took.max(t);
    }
    eprintln!(
        "100 sources churning, {threads} threads ({opened} connects in {took:.1?}, {:.0}/s): {served}/10 served, ms {ms:?}",
        opened as f64 / took.as_secs_f64()
    );
    assert!(served >= 8, "churn: {served}/10, {ms:?}");
    assert!(ok.contains("Verify return code: 0 (ok)"), "{ok}");
    drop(m);
    let log = gw.log();
    let gave_way = log.matches("the oldest unfinished one gave way").count();
    assert!(
        (1..=200).contains(&gave_way),
        "each source said once a minute: {gave_way} lines"
    );
    let stats = counters(&mut gw);
    assert_eq!(stats["connections_refused"], 0, "{stats:?}");
    assert!(stats["tls_failed"] >= 530, "{stats:?}");
}

/// mbgate as a TLS client of a device (pymodbus' ModbusTlsServer requiring a client
/// certificate): it verifies the device against device_ca and presents its own
/// certificate; a plain master reads through it. With a device_ca that did not sign
/// the device's certificate, nothing is sent to the device and masters get 0x0A.
#[test]
fn the_gateway_reaches_a_device_behind_tls_and_verifies_it() {
    let dir = tempdir();
    let pki = pki(dir.path());
    pki.sign(
        "device",
        "ca",
        "/CN=device",
        "subjectAltName=IP:127.0.0.1\n",
        30,
    );
    pki.master("gw-client", "ca", None, 30);
    let port = free_port();
    let _device = Py::start(
        "tls_device.py",
        &[
            "--port",
            &port.to_string(),
            "--cert",
            &pki.pem("device"),
            "--key",
            &pki.key("device"),
            "--ca",
            &pki.pem("ca"),
        ],
    );
    let line = |ca: &str| {
        format!(
            "[[line]]\n[line.tcp]\naddress = \"127.0.0.1:{port}\"\n\
             tls = {{ cert = {:?}, key = {:?}, device_ca = {:?} }}\n\n\
             [[listen]]\naddress = \"127.0.0.1:0\"\n\n[log]\nlevel = \"debug\"\n",
            pki.pem("gw-client"),
            pki.key("gw-client"),
            pki.pem(ca)
        )
    };
    let (mut gw, addrs) = gateway_from_file(dir.path(), &line("ca"), 1);
    gw.wait_log("device socket open", Duration::from_secs(10));
    let mut m = connect(addrs[0]);
    assert_eq!(
        transact(&mut m, &read_req(1, 1, 3, 2)),
        read_reply(1, 1, &[1003, 1004])
    );
    assert_eq!(
        transact(&mut m, &req(2, &[6, 0, 3, 0, 9])),
        req(2, &[6, 0, 3, 0, 9])
    );
    assert!(gw.terminate(Duration::from_secs(10)).success());

    let dir2 = tempdir();
    let (mut gw, addrs) = gateway_from_file(dir2.path(), &line("other"), 1);
    gw.wait_log("TLS handshake with the device", Duration::from_secs(10));
    let mut m = connect(addrs[0]);
    assert_eq!(
        transact(&mut m, &read_req(3, 1, 3, 1)),
        exception(3, 3, 0x0A)
    );
    assert!(gw.terminate(Duration::from_secs(10)).success());
}
