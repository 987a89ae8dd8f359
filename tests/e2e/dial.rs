//! The gateway dials its master (`[[dial]]`, docs/dialing.md): the real binary, a
//! pymodbus RTU server on a socat pty pair as the device, and tests/py/dial_server.py
//! as the SCADA server: it listens, takes mbgate's connection, reads the identity and
//! sends requests framed by pymodbus, checking every reply by value. The server is
//! late (mbgate is refused first), closes at once, sends garbage, closes before a
//! reply, echoes the identity and the heartbeat: mbgate dials again each time, the
//! echoes are never taken for requests, and the log says the outage once. Modbus over
//! UDP (`transport = "udp"`) with pymodbus' UDP clients as masters, malformed
//! datagrams counted, and a flood from one source beside a polite master.

use crate::common;
use common::*;
use std::time::Duration;

/// socat, pymodbus' RTU server on the device end, and the gateway's configuration
/// for the other end (to which a test adds its `[[dial]]` or `[[listen]]` tables).
struct Bench {
    dir: tempfile::TempDir,
    _socat: Socat,
    _device: Py,
    cfg: String,
}

fn bench() -> Bench {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let args = ["--port", socat.dev.to_str().unwrap(), "--framer", "rtu"];
    let device = Py::start("stock_server.py", &args);
    let cfg = format!(
        "[[line]]\nserial = {{ path = {:?}, framing = \"rtu\", flow_control = \"none\", baud_rate = 4000000 }}\n\
         relay = {{ response_timeout_ms = 5000 }}\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\n\
         [log]\nlevel = \"debug\"\n[metrics]\nlisten = \"127.0.0.1:0\"\n",
        socat.gw.to_str().unwrap()
    );
    Bench {
        dir,
        _socat: socat,
        _device: device,
        cfg,
    }
}

/// The dial table every dial test uses, to `port`: short backoff bounds so the
/// rounds follow each other within seconds.
fn dial(port: u16, extra: &str) -> String {
    format!(
        "[[dial]]\naddress = \"127.0.0.1:{port}\"\nidentity = \"site-17\"\n\
         backoff_min_ms = 100\nbackoff_max_ms = 400\n{extra}"
    )
}

/// A gateway dialing a dial_server.py on a free port (the dial's extra keys
/// `extra`), the server run to its end with `server` arguments beside `--listen` and
/// `--identity`: the bench (kept alive), the gateway and what the server printed.
fn dialed(extra: &str, server: &[&str]) -> (Bench, Gateway, String) {
    let b = bench();
    let port = free_port();
    let text = format!("{}{}", b.cfg, dial(port, extra));
    let gw = Gateway::launch_text(&text, b.dir.path(), Launch::default());
    let listen = format!("127.0.0.1:{port}");
    let mut args = vec!["--listen", &listen, "--identity", "site-17"];
    args.extend_from_slice(server);
    let (status, out) = Py::run("dial_server.py", &args);
    assert!(status.success(), "{out}\n{}", gw.log());
    (b, gw, out)
}

/// The server is not there yet (refused), then comes; it closes at once, sends
/// garbage, closes before a reply, and at last serves: every reply it gets is right,
/// the log warns of the outage once and says once that the dial is back.
#[test]
fn a_dialed_master_is_served_through_refusals_garbage_and_hangups() {
    let b = bench();
    let port = free_port();
    let text = format!("{}{}", b.cfg, dial(port, ""));
    let mut gw = Gateway::launch_text(&text, b.dir.path(), Launch::default());
    gw.wait_log("dial[0] (127.0.0.1:", Duration::from_secs(10));
    assert!(
        gw.log().contains("Connection refused"),
        "nobody listens yet: {}",
        gw.log()
    );
    let listen = format!("127.0.0.1:{port}");
    let rounds = ["close", "garbage", "halfway", "serve"];
    let mut args = vec!["--listen", &listen, "--identity", "site-17"];
    for r in rounds {
        args.extend(["--round", r]);
    }
    let (status, out) = Py::run("dial_server.py", &args);
    assert!(status.success(), "{out}\n{}", gw.log());
    assert!(out.contains("serve ok 10") && out.contains("DONE"), "{out}");
    // The server closes after its last round, and that outage is said too, once the
    // gateway has read the close: on a loaded machine after the script has ended.
    let said = |log: &str| log.matches("dialing again with backoff").count();
    let until = std::time::Instant::now() + Duration::from_secs(10);
    while said(&gw.log()) < 2 && std::time::Instant::now() < until {
        std::thread::sleep(Duration::from_millis(20));
    }
    let log = gw.log();
    // The outage from the refusal to the served round, said once; back, said once;
    // and the one the server's close begins.
    let warned = said(&log);
    let back = log.matches("connected to 127.0.0.1:").count();
    assert_eq!((warned, back), (2, 1), "{log}");
    assert!(log.contains("protocol violation"), "the garbage: {log}");
    let counters = gw.stop();
    // The garbage's first bytes were taken for the identity's answer, the next not.
    assert_eq!(counters["dial_answers"], 1, "{counters:?}");
    assert!(counters["connections"] >= 4, "{counters:?}");
    assert!(counters["requests"] >= 11, "{counters:?}");
}

/// A server that echoes the identity and the heartbeat: the echoes are dropped, the
/// requests after them answered by value; the heartbeat came while no request did.
#[test]
fn echoes_of_the_identity_and_the_heartbeat_are_not_requests() {
    let hb = "heartbeat = \"hex:ff fe 00 01\"\nheartbeat_ms = 300\n";
    let server = ["--heartbeat", "fffe0001", "--round", "echo"];
    let (_b, mut gw, out) = dialed(hb, &server);
    assert!(out.contains("echo ok 10"), "{out}");
    let log = gw.log();
    assert!(!log.contains("protocol violation"), "{log}");
    assert!(
        log.contains("the server echoed the identity or a heartbeat"),
        "{log}"
    );
    let counters = gw.stop();
    assert_eq!(counters["protocol_violations"], 0, "{counters:?}");
}

/// `[[listen]]` with `transport = "udp"` and pymodbus' sync and async UDP clients as
/// masters: every value right; malformed datagrams dropped and counted, exactly.
#[test]
fn udp_masters_are_answered_and_malformed_datagrams_counted() {
    let (_b, mut gw, out) = udp_masters(&["--malformed", "5"]);
    assert!(out.contains("sync ok") && out.contains("async ok"), "{out}");
    let counters = gw.stop();
    assert_eq!(counters["datagrams_dropped"], 5, "{counters:?}");
    assert_eq!(counters["protocol_violations"], 0, "{counters:?}");
}

/// 10 000 datagrams from one source beside a polite master: the polite master's
/// every request is answered by value; the flood gets no more than its share, the
/// rest dropped and counted.
#[test]
fn a_udp_flood_from_one_source_leaves_a_polite_master_its_share() {
    let (_b, mut gw, out) = udp_masters(&["--flood", "10000"]);
    assert!(out.contains("polite ok 40"), "{out}");
    let flood_replies: u64 = out
        .lines()
        .find_map(|l| l.strip_prefix("flood replies "))
        .and_then(|n| n.trim().parse().ok())
        .unwrap_or_else(|| panic!("{out}"));
    let counters = gw.stop();
    eprintln!(
        "flood: {flood_replies} replies to the flood, datagrams_dropped={}, requests={}",
        counters["datagrams_dropped"], counters["requests"]
    );
    assert!(counters["datagrams_dropped"] > 0, "{counters:?}");
    assert!(flood_replies < 10_000, "{flood_replies}");
    // What reached the line: the polite master's 40 and the flood's replies at most.
    assert!(
        counters["requests"] <= 40 + 10_000 - counters["datagrams_dropped"],
        "{counters:?}"
    );
}

/// A gateway with a UDP listener, and tests/py/udp_master.py run against it to its end
/// with `args`: the bench (kept alive), the gateway and what the masters printed.
fn udp_masters(args: &[&str]) -> (Bench, Gateway, String) {
    let b = bench();
    let text = format!(
        "{}[[listen]]\naddress = \"127.0.0.1:0\"\ntransport = \"udp\"\n",
        b.cfg
    );
    let gw = Gateway::launch_text(&text, b.dir.path(), Launch::default());
    let port = udp_addr(&gw).port().to_string();
    let mut all = vec!["--port", &port];
    all.extend_from_slice(args);
    let (status, out) = Py::run("udp_master.py", &all);
    assert!(status.success(), "{out}\n{}", gw.log());
    (b, gw, out)
}

/// The UDP listener's address, as the log says it (a line after the one the launch
/// waited for: waited for too).
fn udp_addr(gw: &Gateway) -> std::net::SocketAddr {
    gw.wait_log("for Modbus/UDP masters", Duration::from_secs(10));
    let log = gw.log();
    log.lines()
        .find(|l| l.contains("for Modbus/UDP masters"))
        .and_then(|l| l.split("listening on ").nth(1))
        .and_then(|r| r.split_whitespace().next())
        .and_then(|a| a.parse().ok())
        .unwrap_or_else(|| panic!("no UDP listener in the log:\n{log}"))
}

/// tests/py/dial_server.py as a child whose stdout lines come through a channel and
/// whose stdin the test writes (the `keep` round waits for a line).
struct Server {
    child: std::process::Child,
    lines: std::sync::mpsc::Receiver<String>,
    said: Vec<String>,
}

impl Server {
    fn start(args: &[&str]) -> Server {
        use std::io::BufRead;
        use std::process::{Command, Stdio};
        let mut child = Command::new(python())
            .arg(repo().join("tests/py/dial_server.py"))
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("start python");
        let out = std::io::BufReader::new(child.stdout.take().unwrap());
        let (tx, lines) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for l in out.lines().map_while(Result::ok) {
                let _ = tx.send(l);
            }
        });
        let mut s = Server {
            child,
            lines,
            said: Vec::new(),
        };
        s.expect("READY");
        s
    }

    /// Waits (bounded) for a line that starts with `what`.
    fn expect(&mut self, what: &str) -> String {
        let until = std::time::Instant::now() + Duration::from_secs(30);
        while let Some(left) = until.checked_duration_since(std::time::Instant::now()) {
            match self.lines.recv_timeout(left) {
                Ok(l) if l.starts_with(what) => return l,
                Ok(l) => self.said.push(l),
                Err(_) => break,
            }
        }
        panic!("no {what:?} from dial_server.py; it said {:?}", self.said);
    }

    /// On 127.0.0.1:`port`, the identity `site-17`, and `args`.
    fn at(port: u16, args: &[&str]) -> Server {
        let listen = format!("127.0.0.1:{port}");
        let mut all = vec!["--listen", &listen, "--identity", "site-17"];
        all.extend_from_slice(args);
        Server::start(&all)
    }

    fn go_on(&mut self) {
        use std::io::Write;
        let stdin = self.child.stdin.as_mut().unwrap();
        stdin.write_all(b"go\n").unwrap();
        stdin.flush().unwrap();
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A reload adds a dial while the one unchanged keeps its connection (the server
/// checks replies on it before and after), then changes it (it dials again with its
/// new identity) and removes the other.
#[test]
fn a_reload_adds_changes_and_removes_dials_and_leaves_the_others_be() {
    let b = bench();
    let (p1, p2) = (free_port(), free_port());
    let (a1, a2) = (format!("127.0.0.1:{p1}"), format!("127.0.0.1:{p2}"));
    let file = b.dir.path().join("mbgate.toml");
    let mut first = Server::start(&["--listen", &a1, "--identity", "site-17", "--round", "keep"]);
    let mut gw = Gateway::launch_text(
        &format!("{}{}", b.cfg, dial(p1, "")),
        b.dir.path(),
        Launch::default(),
    );
    first.expect("kept 10");
    // Add a dial; the first is unchanged.
    let mut second = Server::start(&["--listen", &a2, "--identity", "site-17", "--round", "serve"]);
    std::fs::write(&file, format!("{}{}{}", b.cfg, dial(p1, ""), dial(p2, ""))).unwrap();
    gw.proc.signal("HUP");
    second.expect("serve ok 10");
    first.go_on();
    first.expect("keep ok 20");
    let log = gw.log();
    assert!(log.contains(&format!("dial \"{a2}\" added")), "{log}");
    // SIGUSR1's counters count the dial the reload added: 20 requests and 10.
    gw.proc.signal("USR1");
    gw.wait_log("counters (SIGUSR1)", Duration::from_secs(10));
    let log = gw.log();
    let usr1 = log
        .lines()
        .find(|l| l.contains("counters (SIGUSR1)"))
        .unwrap();
    assert!(usr1.contains(" requests=30 "), "{usr1}");
    // Change the first (its identity), remove the second. The first server has
    // ended its round and closed, so the dial as it was dials again meanwhile: the
    // new server listens only once the reload has changed the dial, else the old
    // dial's identity could reach it first (its own right, before the reload).
    let changed = dial(p1, "").replace("site-17", "site-18");
    std::fs::write(&file, format!("{}{changed}", b.cfg)).unwrap();
    gw.proc.signal("HUP");
    gw.wait_log(
        &format!("dial \"{a1}\" changed (dialing again)"),
        Duration::from_secs(10),
    );
    let mut third = Server::start(&["--listen", &a1, "--identity", "site-18", "--round", "serve"]);
    third.expect("serve ok 10");
    let log = gw.log();
    assert!(
        log.contains(&format!("dial \"{a1}\" changed (dialing again)")),
        "{log}"
    );
    assert!(log.contains(&format!("dial \"{a2}\" removed")), "{log}");
    // The removed dial is off the metrics, the changed one (same address) on them.
    let metrics = gw.http_get("/metrics");
    assert!(!metrics.contains(&format!("\"dial {a2}\"")), "{metrics}");
    assert!(metrics.contains(&format!("\"dial {a1}\"")), "{metrics}");
    // The totals at the stop count every dial that ran: the removed one's 10 too.
    let counters = gw.stop();
    assert_eq!(counters["requests"], 40, "{counters:?}");
    assert_eq!(counters["protocol_violations"], 0, "{counters:?}");
}

/// Modbus/TCP Security with mbgate as the client: a server whose certificate chains
/// to another CA is refused (and dialed again, the outage said once); the right one
/// is served, its role (`viewer`, read only) taken from its certificate: reads
/// answered by value, a write answered 0x01.
#[test]
fn a_tls_dial_checks_the_server_and_takes_its_role_from_its_certificate() {
    if !peer("openssl", "openssl") {
        return;
    }
    let b = bench();
    let pki = common::pki::Pki::new(&b.dir.path().join("pki"));
    let san = "subjectAltName=IP:127.0.0.1,DNS:localhost\n";
    let role = format!("{san}{}viewer\n", common::pki::ROLE_EXT);
    pki.sign("scada", "ca", "/CN=scada", &role, 30);
    pki.ca("other");
    pki.sign("stranger", "other", "/CN=stranger", &role, 30);
    let port = free_port();
    let tls = format!(
        "tls = {{ cert = {:?}, key = {:?}, server_ca = {:?} }}\n",
        pki.pem("gateway"),
        pki.key("gateway"),
        pki.pem("ca")
    );
    let text = format!(
        "{}{}[[role]]\nname = \"viewer\"\nread_only = true\n",
        b.cfg,
        dial(port, &tls)
    );
    let mut gw = Gateway::launch_text(&text, b.dir.path(), Launch::default());
    let listen = format!("127.0.0.1:{port}");
    let right = format!(
        "{}:{}:{}",
        pki.pem("scada"),
        pki.key("scada"),
        pki.pem("ca")
    );
    let wrong = format!("{}:{}", pki.pem("stranger"), pki.key("stranger"));
    let args = [
        "--listen",
        &listen,
        "--identity",
        "site-17",
        "--tls",
        &right,
        "--wrong",
        &wrong,
        "--round",
        "refused",
        "--round",
        "readonly",
    ];
    let (status, out) = Py::run("dial_server.py", &args);
    assert!(status.success(), "{out}\n{}", gw.log());
    assert!(
        out.contains("refused ok") && out.contains("readonly ok 6"),
        "{out}"
    );
    let log = gw.log();
    assert!(log.contains("TLS handshake failed"), "{log}");
    assert_eq!(log.matches("connected to 127.0.0.1:").count(), 1, "{log}");
    let counters = gw.stop();
    assert_eq!(counters["tls_failed"], 1, "{counters:?}");
    assert_eq!(counters["denied"], 1, "{counters:?}");
}

/// A server that sends requests and never reads the replies: once mbgate's socket can
/// take no more, the connection is closed after `connect_timeout_ms` (a dial's
/// `idle_timeout_ms` being 0), never held for ever, and dialed again.
#[test]
fn a_server_that_never_reads_is_given_up_and_dialed_again() {
    let b = bench();
    let port = free_port();
    let args = ["--rcvbuf", "4096", "--round", "deaf", "--round", "serve"];
    let mut server = Server::at(port, &args);
    let text = format!("{}{}", b.cfg, dial(port, "connect_timeout_ms = 1000\n"));
    let mut gw = Gateway::launch_text(&text, b.dir.path(), Launch::default());
    server.expect("deaf sent");
    gw.wait_log("stopped reading its replies", Duration::from_secs(60));
    server.go_on();
    server.expect("deaf ok");
    server.expect("serve ok 10");
    let log = gw.log();
    assert!(
        log.contains("ended: the master stopped reading its replies"),
        "{log}"
    );
    gw.stop();
}

/// What a run of server restarts left: the log, the counters at the stop, what the
/// server printed at its end, the accepted master's reads, and the gateway's file
/// descriptors and memory before and after.
struct Restarted {
    log: String,
    counters: std::collections::HashMap<String, u64>,
    said: String,
    polled: u16,
    fds: (usize, usize),
    rss_kib: (u64, u64),
}

/// The server killed and started again `n` times (dial_server.py `--restarts`, with
/// `args` beside) while an accepted master keeps the line busy, each of its reads
/// checked by value: the first and the last connection held while the test looks at
/// the gateway's file descriptors and memory.
fn restarts(n: usize, args: &[&str]) -> Restarted {
    use std::sync::atomic::{AtomicBool, Ordering};
    let b = bench();
    let port = free_port();
    let listen = format!("127.0.0.1:{port}");
    let times = n.to_string();
    let mut all = vec!["--restarts", &times];
    all.extend_from_slice(args);
    let mut server = Server::at(port, &all);
    let text = format!(
        "{}[[dial]]\naddress = \"{listen}\"\nidentity = \"site-17\"\n\
         backoff_min_ms = 20\nbackoff_max_ms = 200\n",
        b.cfg
    );
    let mut gw = Gateway::launch_text(&text, b.dir.path(), Launch::default());
    // The accepted master: reads throughout, each checked by value.
    let stop = std::sync::Arc::new(AtomicBool::new(false));
    let mut m = gw.connect();
    let busy = {
        let stop = stop.clone();
        std::thread::spawn(move || {
            let mut n = 0u16;
            while !stop.load(Ordering::Relaxed) {
                let addr = 1 + n % 50;
                let got = transact(&mut m, &read_req(n, 1, addr, 1));
                assert_eq!(got, read_reply(n, 1, &[1000 + addr]), "read {n}");
                n = n.wrapping_add(1);
            }
            n
        })
    };
    let fds = |gw: &Gateway| {
        std::fs::read_dir(format!("/proc/{}/fd", gw.proc.pid()))
            .unwrap()
            .count()
    };
    server.expect("held");
    let (fds_before, mem_before) = (fds(&gw), mem(&gw));
    // The dialed master on the metrics as a listener's, beside the accepted one.
    let metrics = gw.http_get("/metrics");
    let dialed =
        format!("mbgate_listener_masters{{listener=\"dial {listen}\",transport=\"tcp\"}} 1");
    assert!(metrics.contains(&dialed), "{metrics}");
    assert_eq!(gw.metric("mbgate_listener_masters"), 2.0, "{metrics}");
    server.go_on();
    server.expect("held");
    // The last connection held, and said so: each of the restarts and the first
    // connection's end was an outage, each over once the next connection held.
    let count = |gw: &Gateway, what: &str| gw.log().matches(what).count();
    wait_for("every return", Duration::from_secs(20), || {
        count(&gw, "again, after") > n
    });
    let (fds_after, mem_after) = (fds(&gw), mem(&gw));
    server.go_on();
    let said = server.expect(&format!("restarts ok {n}"));
    wait_for("the last outage", Duration::from_secs(20), || {
        count(&gw, "dialing again with backoff") >= n + 2
    });
    stop.store(true, Ordering::Relaxed);
    let polled = busy
        .join()
        .expect("every read of the accepted master right");
    let log = gw.log();
    let counters = gw.stop();
    Restarted {
        log,
        counters,
        said,
        polled,
        fds: (fds_before, fds_after),
        rss_kib: (mem_before.rss_kib, mem_after.rss_kib),
    }
}

/// The server killed and started again 50 times while another master keeps the line
/// busy: every reply either master got is right, the gateway holds as many file
/// descriptors after as before (and about the memory), and the log says each outage
/// once and each return once.
#[test]
fn fifty_server_restarts_under_load_leave_nothing_behind() {
    let r = restarts(50, &[]);
    eprintln!(
        "restarts: {} reads beside; fds {:?}; RSS {:?} KiB",
        r.polled, r.fds, r.rss_kib
    );
    assert_eq!(r.fds.1, r.fds.0);
    assert!(r.rss_kib.1 < r.rss_kib.0 + 2048, "RSS {:?} KiB", r.rss_kib);
    // 52 connections, each ended: each end said once, each return once.
    let outages = r.log.matches("dialing again with backoff").count();
    let back = r.log.matches("again, after").count();
    assert_eq!((outages, back), (52, 51), "{}", r.log);
    assert_eq!(r.counters["protocol_violations"], 0, "{:?}", r.counters);
}

/// The server restarts every second, busy to its end: for a second it sends reads
/// and checks every reply by value, then sends one more and is gone before its reply.
/// The gateway dials again each time, the log says each outage once and each return
/// once, nothing is left behind, and no reply was wrong on either master.
#[test]
fn a_server_restarting_every_second_under_load_is_dialed_again_each_time() {
    let r = restarts(10, &["--busy", "--hold", "1.0"]);
    let replies: u64 = r
        .said
        .rsplit(' ')
        .next()
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("{}", r.said));
    eprintln!(
        "busy restarts: {replies} replies checked by the server, {} reads beside; fds {:?}",
        r.polled, r.fds
    );
    // Each restart's second was served (the device answers in a few ms).
    assert!(replies >= 10 * 3, "{}", r.said);
    assert_eq!(r.fds.1, r.fds.0);
    let outages = r.log.matches("dialing again with backoff").count();
    let back = r.log.matches("again, after").count();
    assert_eq!((outages, back), (12, 11), "{}", r.log);
    assert_eq!(r.counters["protocol_violations"], 0, "{:?}", r.counters);
    // Every request of the server's reached the line once: its checked replies, the
    // last read of each restart (at most), the first and last connections' checks,
    // and the accepted master's reads.
    let asked = replies + 10 + 2 * 10 + u64::from(r.polled);
    assert!(r.counters["requests"] <= asked + 1, "{:?}", r.counters);
}

/// A server that answers the identity and two heartbeats with bytes of its own
/// ("ACK", "HB-ACK"): each answer is dropped and counted, the connection kept, no
/// answer reaches the line (the requests the line got are exactly the server's), and
/// every request after them is answered by value.
#[test]
fn a_server_answering_the_heartbeat_is_tolerated_and_never_relayed() {
    heartbeat_answers_dropped("", &[]);
}

/// The same on a dial with `framing = "rtu"`: the answers are no RTU request (their
/// CRC fails), and the requests after them are framed by pymodbus' RTU framer.
#[test]
fn an_rtu_dial_tolerates_answers_to_its_heartbeat() {
    heartbeat_answers_dropped("framing = \"rtu\"\n", &["--framer", "rtu"]);
}

/// A dial (its extra keys `dial`) to dial_server.py's `ack` round (its extra
/// arguments `server`): the three answers dropped and counted, on /metrics too, the
/// 30 requests after them answered, one connection, no violation.
fn heartbeat_answers_dropped(dial: &str, server: &[&str]) {
    let keys = format!("{dial}heartbeat = \"hex:ff fe 00 01\"\nheartbeat_ms = 1000\n");
    let mut args = vec!["--heartbeat", "fffe0001", "--round", "ack"];
    args.extend_from_slice(server);
    let (_b, mut gw, out) = dialed(&keys, &args);
    assert!(out.contains("ack ok 30"), "{out}");
    let log = gw.log();
    assert!(!log.contains("protocol violation"), "{log}");
    // On /metrics too, as the dial's (a listener's) counter.
    assert_eq!(gw.metric("mbgate_listener_dial_answers"), 3.0);
    let counters = gw.stop();
    assert_eq!(counters["dial_answers"], 3, "{counters:?}");
    assert_eq!(counters["protocol_violations"], 0, "{counters:?}");
    assert_eq!(counters["connections"], 1, "{counters:?}");
    assert_eq!(counters["requests"], 30, "{counters:?}");
    assert_eq!(counters["bad_requests"], 0, "{counters:?}");
}

/// `framing = "rtu"` on a dial: the server sends RTU over TCP (pymodbus' RTU framer),
/// every reply checked by value.
#[test]
fn a_dial_speaks_rtu_over_tcp() {
    let server = ["--framer", "rtu", "--round", "serve"];
    let (_b, mut gw, out) = dialed("framing = \"rtu\"\n", &server);
    assert!(out.contains("serve ok 10"), "{out}");
    let counters = gw.stop();
    assert_eq!(counters["protocol_violations"], 0, "{counters:?}");
}

/// A reload changes a UDP listener (now read only), adds one and then removes one;
/// the TCP listener is untouched throughout (its master keeps its connection).
#[test]
fn a_reload_adds_changes_and_removes_udp_listeners() {
    let b = bench();
    let (p1, p2) = (free_udp_port(), free_udp_port());
    let (u1, u2) = (format!("127.0.0.1:{p1}"), format!("127.0.0.1:{p2}"));
    let udp = |addr: &str, extra: &str| {
        format!("[[listen]]\naddress = {addr:?}\ntransport = \"udp\"\n{extra}")
    };
    let file = b.dir.path().join("mbgate.toml");
    let text = format!("{}{}", b.cfg, udp(&u1, ""));
    let mut gw = Gateway::launch_text(&text, b.dir.path(), Launch::default());
    let mut m = gw.connect();
    let write = write_req(7, 1, 150, &[42]);
    let written = udp_transact(&u1, &write).unwrap();
    assert_eq!(written[7], 0x10, "the write passes: {written:02X?}");
    // u1 read only, u2 new.
    std::fs::write(
        &file,
        format!(
            "{}{}{}",
            b.cfg,
            udp(&u1, "read_only = true\n"),
            udp(&u2, "")
        ),
    )
    .unwrap();
    gw.proc.signal("HUP");
    gw.wait_log(
        &format!("listen \"{u2} (UDP)\" (new in the file)"),
        Duration::from_secs(10),
    );
    let denied = udp_transact(&u1, &write).unwrap();
    assert_eq!(&denied[7..], [0x90, 0x01], "read only now: {denied:02X?}");
    for to in [&u1, &u2] {
        assert_eq!(
            udp_transact(to, &read_req(3, 1, 150, 1)).unwrap(),
            read_reply(3, 1, &[42])
        );
    }
    assert!(gw
        .log()
        .contains(&format!("listen \"{u1} (UDP)\" changed (started again)")));
    // u1 gone.
    std::fs::write(&file, format!("{}{}", b.cfg, udp(&u2, ""))).unwrap();
    gw.proc.signal("HUP");
    gw.wait_log(
        &format!("listen \"{u1} (UDP)\" (gone from the file)"),
        Duration::from_secs(10),
    );
    // Requests served while u1 closes (one more may reach the line unanswered).
    let mut served = 0;
    wait_for("u1 closed", Duration::from_secs(10), || {
        let closed = udp_transact(&u1, &read_req(4, 1, 150, 1)).is_err();
        served += u64::from(!closed);
        closed
    });
    let metrics = gw.http_get("/metrics");
    assert!(!metrics.contains(&format!("\"{u1}\"")), "u1 off: {metrics}");
    assert!(metrics.contains(&format!("\"{u2}\"")), "{metrics}");
    assert_eq!(
        udp_transact(&u2, &read_req(5, 1, 150, 1)).unwrap(),
        read_reply(5, 1, &[42])
    );
    // The TCP master's connection went through both reloads.
    assert_eq!(
        transact(&mut m, &read_req(6, 1, 150, 1)),
        read_reply(6, 1, &[42])
    );
    // The totals count u2, added by a reload (2 requests), and u1, removed by one.
    let counters = gw.stop();
    let requests = counters["requests"];
    assert!(
        (5 + served..=6 + served).contains(&requests),
        "{served} served while closing: {counters:?}"
    );
}

/// The sockets `pid` listens on (TCP, IPv4 and IPv6): its socket inodes found in
/// /proc/net/tcp and tcp6 in the LISTEN state, as `ADDR:PORT` in the kernel's hex.
fn listening(pid: u32) -> Vec<String> {
    let inodes: Vec<String> = std::fs::read_dir(format!("/proc/{pid}/fd"))
        .unwrap()
        .filter_map(|e| std::fs::read_link(e.ok()?.path()).ok())
        .filter_map(|l| {
            let l = l.to_string_lossy().into_owned();
            Some(l.strip_prefix("socket:[")?.strip_suffix(']')?.to_owned())
        })
        .collect();
    let mut out = Vec::new();
    for table in ["/proc/net/tcp", "/proc/net/tcp6"] {
        let text = std::fs::read_to_string(table).unwrap_or_default();
        for row in text.lines().skip(1) {
            let f: Vec<&str> = row.split_whitespace().collect();
            // local_address, state (0A: LISTEN), inode.
            if f.len() > 9 && f[3] == "0A" && inodes.iter().any(|i| i == f[9]) {
                out.push(f[1].to_owned());
            }
        }
    }
    out
}

/// A file of `[[line]]` and `[[dial]]` alone (docs/dialing.md's Raspberry Pi) opens
/// no port: `check-config` says so, and the running gateway listens on nothing
/// (before: 0.0.0.0:502, read and write for anyone). `--listen` opens one; the
/// listener's other flags alone are refused, naming what to give.
#[test]
fn a_file_that_only_dials_opens_no_port() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let file = dir.path().join("mbgate.toml");
    std::fs::write(
        &file,
        format!(
            "[[line]]\nserial = {{ path = {:?}, framing = \"rtu\", flow_control = \"none\" }}\n\n\
             [[dial]]\naddress = \"127.0.0.1:{}\"\nheartbeat = \"hex:ff fe 00 01\"\n\
             [log]\nlevel = \"debug\"\n",
            socat.gw.to_str().unwrap(),
            free_port()
        ),
    )
    .unwrap();
    let path = file.to_str().unwrap();
    let checked = mbgate(&["check-config", path]);
    assert_eq!(checked.code, 0, "{}", checked.stderr);
    assert!(
        checked.stdout.contains(
            "no listener: the file only dials its masters and opens no port (add [[listen]]"
        ) && !checked.stdout.contains("listening on"),
        "{}",
        checked.stdout
    );
    let refused = mbgate(&["check-config", path, "--max-connections", "5"]);
    assert_ne!(refused.code, 0);
    assert!(refused.stderr.contains("--max-connections: the file only dials its masters and opens no listener: give --listen ADDR too"), "{}", refused.stderr);
    let opened = mbgate(&["check-config", path, "--listen", "127.0.0.1:0"]);
    assert!(
        opened
            .stdout
            .contains("listening on 127.0.0.1:0 for Modbus/TCP masters"),
        "{}",
        opened.stdout
    );
    // Nobody else listens on 502 here (else the connect below proves nothing of ours).
    let others = std::net::TcpStream::connect("127.0.0.1:502").is_ok();
    let mut gw = Proc::start(&["run", "--config", path], "dial[0]: dialing");
    assert!(
        gw.log()
            .contains("no listener: the file only dials its masters and opens no port"),
        "{}",
        gw.log()
    );
    assert_eq!(listening(gw.pid()), Vec::<String>::new(), "{}", gw.log());
    if !others {
        assert!(std::net::TcpStream::connect("127.0.0.1:502").is_err());
    }
    assert!(!gw.log().contains("listening on"), "{}", gw.log());
    assert!(gw.terminate(Duration::from_secs(10)).success());
    // With --listen, the one named.
    let mut gw = Proc::start(
        &["run", "--config", path, "--listen", "127.0.0.1:0"],
        "listening on 127.0.0.1:",
    );
    assert_eq!(listening(gw.pid()).len(), 1, "{}", gw.log());
    assert!(gw.terminate(Duration::from_secs(10)).success());
}

/// A server whose certificate chains to the dial's CA but carries no role, on a dial
/// with no `tls.default_role`: refused after the handshake, counted, and the log says
/// it in a dial's words (before: "the listener has no default_role").
#[test]
fn a_tls_dial_refuses_a_server_without_a_role_in_its_own_words() {
    if !peer("openssl", "openssl") {
        return;
    }
    let b = bench();
    let pki = common::pki::Pki::new(&b.dir.path().join("pki"));
    pki.sign(
        "norole",
        "ca",
        "/CN=scada",
        "subjectAltName=IP:127.0.0.1,DNS:localhost\n",
        30,
    );
    let port = free_port();
    let tls = format!(
        "tls = {{ cert = {:?}, key = {:?}, server_ca = {:?} }}\n",
        pki.pem("gateway"),
        pki.key("gateway"),
        pki.pem("ca")
    );
    let mut gw = Gateway::launch_text(
        &format!("{}{}", b.cfg, dial(port, &tls)),
        b.dir.path(),
        Launch::default(),
    );
    let listen = format!("127.0.0.1:{port}");
    let cert = format!(
        "{}:{}:{}",
        pki.pem("norole"),
        pki.key("norole"),
        pki.pem("ca")
    );
    let args = [
        "--listen",
        &listen,
        "--identity",
        "site-17",
        "--tls",
        &cert,
        "--round",
        "refused",
    ];
    let (status, out) = Py::run("dial_server.py", &args);
    assert!(status.success(), "{out}\n{}", gw.log());
    gw.wait_log("dial has no tls.default_role", Duration::from_secs(10));
    let log = gw.log();
    assert!(
        log.contains("carries no Modbus role and the dial has no tls.default_role"),
        "{log}"
    );
    assert!(!log.contains("the listener has no default_role"), "{log}");
    let counters = gw.stop();
    assert_eq!(counters["tls_refused"], 1, "{counters:?}");
}
