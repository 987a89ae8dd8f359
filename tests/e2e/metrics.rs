//! The metrics listener (docs/watching.md): `mbgate run` with a scripted MBAP
//! device on a socat pty, known traffic from a raw Modbus/TCP master, and the scraped
//! text parsed by the Python `prometheus_client` OpenMetrics parser
//! (tests/py/parse_metrics.py): every counter has the value the traffic makes. And with
//! the listener off (the default), the gateway listens on its Modbus port only.

use crate::common;
use common::*;
use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::process::{Command, Stdio};
use std::time::Duration;

/// A sample expected: name, labels, value.
type Want<'a> = (&'a str, &'a [(&'a str, &'a str)], f64);

/// One sample: its name, its labels in order, its value.
type Samples = BTreeMap<(String, Vec<(String, String)>), f64>;

/// GET `path` from `addr`: (status line, body).
fn get(addr: SocketAddr, path: &str) -> (String, String) {
    let mut s = TcpStream::connect(addr).expect("connect to the metrics listener");
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    write!(s, "GET {path} HTTP/1.1\r\nHost: {addr}\r\n\r\n").unwrap();
    let mut all = String::new();
    s.read_to_string(&mut all).unwrap();
    let (head, body) = all.split_once("\r\n\r\n").expect("a response head");
    (head.lines().next().unwrap().to_owned(), body.to_owned())
}

/// The samples of an exposition, as the Python client's parser reads them.
fn parse(text: &str) -> Samples {
    let mut child = Command::new(python())
        .arg(repo().join("tests/py/parse_metrics.py"))
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run python");
    child
        .stdin
        .take()
        .unwrap()
        .write_all(text.as_bytes())
        .unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "the parser refused the text: {}\n{text}",
        String::from_utf8_lossy(&out.stderr)
    );
    let mut samples = Samples::new();
    for line in String::from_utf8(out.stdout).unwrap().lines() {
        let v: serde_json::Value = serde_json::from_str(line).unwrap();
        let labels = v["labels"].as_object().unwrap();
        let mut labels: Vec<(String, String)> = labels
            .iter()
            .map(|(k, v)| (k.clone(), v.as_str().unwrap().to_owned()))
            .collect();
        labels.sort();
        let name = v["name"].as_str().unwrap().to_owned();
        samples.insert((name, labels), v["value"].as_f64().unwrap());
    }
    samples
}

fn value(samples: &Samples, name: &str, labels: &[(&str, &str)]) -> f64 {
    let mut labels: Vec<(String, String)> = labels
        .iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect();
    labels.sort();
    *samples
        .get(&(name.to_owned(), labels.clone()))
        .unwrap_or_else(|| panic!("no sample {name} {labels:?} in {samples:#?}"))
}

/// The metrics listener's address, from the log.
fn metrics_addr(gw: &Gateway) -> SocketAddr {
    gw.proc.metrics_addr(Duration::from_secs(5))
}

/// FC 03 of one register at `addr`, as a master sends it.
fn read_at(tid: u16, addr: u16) -> Vec<u8> {
    let [t0, t1] = tid.to_be_bytes();
    let [a0, a1] = addr.to_be_bytes();
    vec![t0, t1, 0, 0, 0, 6, 1, 0x03, a0, a1, 0, 1]
}

fn ask(m: &mut TcpStream, req: &[u8]) -> Vec<u8> {
    m.write_all(req).unwrap();
    let mut head = [0u8; 6];
    m.read_exact(&mut head).unwrap();
    let mut rest = vec![0u8; usize::from(u16::from_be_bytes([head[4], head[5]]))];
    m.read_exact(&mut rest).unwrap();
    [head.to_vec(), rest].concat()
}

/// A write a read-only listener denies is answered 0x01 by the listener, never reaches
/// a line, and is counted in `mbgate_listener_denied_requests_total`, not in the line's
/// `mbgate_line_exceptions_total` (docs/watching.md says so).
#[test]
fn a_denied_request_is_counted_by_its_listener_not_as_a_line_exception() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let _dev = RawDevice::start(&socat.dev, register_device(&[1], Duration::ZERO));
    let text = format!(
        "[[line]]\nserial = {{ path = {:?}, baud_rate = 4000000, flow_control = \"none\" }}\n\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\nread_only = true\n\n\
         [metrics]\nlisten = \"127.0.0.1:0\"\n",
        socat.gw.display().to_string()
    );
    let gw = Gateway::launch_text(&text, dir.path(), Launch::default());
    let http = metrics_addr(&gw);
    let mut m = gw.connect();
    for tid in 1..=2 {
        let reply = ask(&mut m, &write_req(tid, 1, 4, &[7]));
        assert_eq!(reply[7..], [0x90, 0x01], "denied: {reply:?}");
    }
    let (_, body) = get(http, "/metrics");
    let samples = parse(&body);
    let denied: f64 = samples
        .iter()
        .filter(|((name, _), _)| name == "mbgate_listener_denied_requests_total")
        .map(|(_, v)| v)
        .sum();
    assert_eq!(denied, 2.0, "{body}");
    let line_0x01: f64 = samples
        .iter()
        .filter(|((name, labels), _)| {
            name == "mbgate_line_exceptions_total"
                && labels.iter().any(|(k, v)| k == "code" && v == "0x01")
        })
        .map(|(_, v)| v)
        .sum();
    assert_eq!(line_0x01, 0.0, "{body}");
}

/// An RTU unit that never answers, backed off after one timeout: of its three
/// requests, one timed out on the line and two were answered 0x0B at once; `mbgate
/// status` counts each (requests = replies + timeouts + backed off) and so does
/// `mbgate_line_backed_off_requests_total`.
#[test]
fn mbgate_status_counts_the_backed_off_requests() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let _dev = RawRtuDevice::start(&socat.dev, rtu_register_device(&[1]));
    let cfg = Cfg::new(&socat.gw)
        .serial("framing = \"rtu\"")
        .serial("flow_control = \"none\"")
        // Unit 2 never answers: the timeout's length does not matter.
        .relay("response_timeout_ms = 200")
        .relay("unit_backoff_after = 1")
        .relay("unit_backoff_ms = 60000")
        .relay("unit_backoff_max_ms = 60000")
        .metrics("listen = \"127.0.0.1:0\"");
    let gw = Gateway::start(&cfg, dir.path());
    let http = metrics_addr(&gw);
    let mut m = gw.connect();
    for tid in 1..=3u16 {
        let reply = transact(&mut m, &read_req(tid, 2, 0, 1));
        assert_eq!(reply[7..], [0x83, 0x0B], "{reply:?}");
    }
    let run = mbgate(&["status", "--metrics", &http.to_string()]);
    let line = socat.gw.to_str().unwrap();
    assert!(
        run.stdout.contains(&format!(
            "line {line}: port open, 1 masters, 3 requests, 0 replies, 1 timeouts, 2 backed off, 0 queued, 0 in flight"
        )),
        "{}",
        run.stdout
    );
    let (_, body) = get(http, "/metrics");
    assert_eq!(
        value(
            &parse(&body),
            "mbgate_line_backed_off_requests_total",
            &[("line", line)]
        ),
        2.0
    );
}

#[test]
fn metrics_count_known_traffic_exactly_and_parse_as_openmetrics() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    // Register 0 answers at once, 1 never, 2 with exception 0x02, 3 after the
    // response timeout (a late reply).
    let _dev = RawDevice::scripted(
        &socat.dev,
        Box::new(|req| {
            let pdu = req.pdu();
            let addr = u16::from_be_bytes([pdu[1], pdu[2]]);
            let [t0, t1] = req.tid().to_be_bytes();
            let ok = vec![t0, t1, 0, 0, 0, 5, 1, 0x03, 0x02, 0x12, 0x34];
            match addr {
                0 => vec![(Duration::ZERO, ok)],
                2 => vec![(Duration::ZERO, vec![t0, t1, 0, 0, 0, 3, 1, 0x83, 0x02])],
                3 => vec![(Duration::from_millis(300), ok)],
                _ => vec![],
            }
        }),
    );
    let cfg = Cfg::new(&socat.gw)
        .pty_line()
        .serial("flow_control = \"none\"")
        .relay("response_timeout_ms = 200")
        .metrics("listen = \"127.0.0.1:0\"");
    let mut gw = Gateway::start(&cfg, dir.path());
    let http = metrics_addr(&gw);
    let mut m = gw.connect();
    for tid in 0..3 {
        let reply = ask(&mut m, &read_at(tid, 0));
        assert_eq!(reply[7..], [0x03, 0x02, 0x12, 0x34]);
    }
    assert_eq!(ask(&mut m, &read_at(3, 1))[7..], [0x83, 0x0B]);
    assert_eq!(ask(&mut m, &read_at(4, 2))[7..], [0x83, 0x02]);
    assert_eq!(ask(&mut m, &read_at(5, 3))[7..], [0x83, 0x0B]);
    gw.wait_log("late reply dropped", Duration::from_secs(3));

    let (status, body) = get(http, "/metrics");
    assert_eq!(status, "HTTP/1.1 200 OK", "{body}");
    let s = parse(&body);
    let line = socat.gw.to_str().unwrap();
    let l = [("line", line)];
    let u = [("line", line), ("unit", "1")];
    let want: &[Want] = &[
        ("mbgate_line_requests_total", &l, 6.0),
        ("mbgate_line_replies_total", &l, 4.0),
        ("mbgate_line_timeouts_total", &l, 2.0),
        ("mbgate_line_late_replies_total", &l, 1.0),
        ("mbgate_line_retries_total", &l, 0.0),
        ("mbgate_line_opens_total", &l, 1.0),
        ("mbgate_line_dropped_bytes_total", &l, 0.0),
        (
            "mbgate_line_dropped_bytes_by_reason_total",
            &[("line", line), ("reason", "too_early")],
            0.0,
        ),
        (
            "mbgate_line_dropped_bytes_by_reason_total",
            &[("line", line), ("reason", "echo")],
            0.0,
        ),
        (
            "mbgate_line_dropped_bytes_by_reason_total",
            &[("line", line), ("reason", "stale")],
            0.0,
        ),
        (
            "mbgate_line_dropped_bytes_by_reason_total",
            &[("line", line), ("reason", "other")],
            0.0,
        ),
        // Six requests of 12 bytes; four replies of 11, one exception of 9.
        ("mbgate_line_sent_bytes_total", &l, 72.0),
        ("mbgate_line_received_bytes_total", &l, 53.0),
        ("mbgate_line_queued", &l, 0.0),
        ("mbgate_line_in_flight", &l, 0.0),
        ("mbgate_line_masters", &l, 1.0),
        ("mbgate_line_port_open", &l, 1.0),
        ("mbgate_unit_requests_total", &u, 6.0),
        ("mbgate_unit_replies_total", &u, 4.0),
        ("mbgate_unit_timeouts_total", &u, 2.0),
        ("mbgate_unit_backed_off", &u, 0.0),
        ("mbgate_unit_reply_seconds_count", &u, 4.0),
        // Each of the six went on the line once, as priority class 0.
        (
            "mbgate_line_queue_wait_seconds_count",
            &[("line", line), ("class", "0")],
            6.0,
        ),
        ("mbgate_config_last_reload_successful", &[], 1.0),
        ("mbgate_config_reloads_total", &[("result", "refused")], 0.0),
        ("mbgate_capture_dropped_packets_total", &[], 0.0),
    ];
    for (name, labels, v) in want {
        assert_eq!(value(&s, name, labels), *v, "{name} {labels:?}\n{body}");
    }
    let exc = |source: &str, code: &str| {
        let labels = [("line", line), ("source", source), ("code", code)];
        value(&s, "mbgate_line_exceptions_total", &labels)
    };
    assert_eq!(exc("device", "0x02"), 1.0);
    assert_eq!(exc("gateway", "0x0B"), 2.0);
    assert_eq!(exc("gateway", "0x0A"), 0.0);
    assert_eq!(exc("gateway", "0x06"), 0.0);
    // The replies came within the line's time, well under a second, and the
    // histogram's buckets are cumulative.
    let le = |b: &str| {
        let labels = [("line", line), ("unit", "1"), ("le", b)];
        value(&s, "mbgate_unit_reply_seconds_bucket", &labels)
    };
    assert_eq!(le("1.0"), 4.0);
    assert_eq!(le("+Inf"), 4.0);
    assert!(le("0.002") <= le("0.05"));
    let busy = value(&s, "mbgate_line_busy_seconds_total", &l);
    assert!(
        (0.4..5.0).contains(&busy),
        "two timeouts of 0.2 s at least: {busy}"
    );
    let listener = gw.addr.to_string();
    let li = [("listener", listener.as_str()), ("transport", "tcp")];
    assert_eq!(value(&s, "mbgate_listener_masters", &li), 1.0);
    assert_eq!(value(&s, "mbgate_listener_connections_total", &li), 1.0);
    assert_eq!(
        value(&s, "mbgate_listener_refused_connections_total", &li),
        0.0
    );
    assert_eq!(
        value(&s, "mbgate_listener_protocol_violations_total", &li),
        0.0
    );

    // Every metric the Grafana dashboard and the alert rules name is one the gateway
    // exports.
    // (A family without a sample now, such as the learned timeouts of a line with a
    // fixed one, is named by its TYPE line.)
    let mut names: std::collections::BTreeSet<&str> = s.keys().map(|(n, _)| n.as_str()).collect();
    names.extend(
        body.lines()
            .filter_map(|l| l.strip_prefix("# TYPE ")?.split(' ').next()),
    );
    let named = [
        (
            "docs/grafana-dashboard.json",
            include_str!("../../docs/grafana-dashboard.json"),
        ),
        (
            "docs/mbgate-alerts.yml",
            include_str!("../../docs/mbgate-alerts.yml"),
        ),
    ];
    for (file, text) in named {
        for word in text.split(|c: char| !(c.is_ascii_alphanumeric() || c == '_')) {
            if word.starts_with("mbgate_") {
                assert!(names.contains(word), "{file} names {word}");
            }
        }
    }

    // The master goes: the gauges follow.
    drop(m);
    wait_for("the master detached", Duration::from_secs(3), || {
        let s = parse(&get(http, "/metrics").1);
        value(&s, "mbgate_listener_masters", &li) == 0.0
            && value(&s, "mbgate_line_masters", &l) == 0.0
    });
    // Read-only, GET only.
    let mut s = TcpStream::connect(http).unwrap();
    write!(s, "POST /metrics HTTP/1.1\r\nContent-Length: 0\r\n\r\n").unwrap();
    let mut r = String::new();
    s.read_to_string(&mut r).unwrap();
    assert!(r.starts_with("HTTP/1.1 405 "), "{r}");
    gw.stop();
}

/// The TCP ports process `pid` listens on, from /proc/net/tcp and tcp6: the sockets
/// in state LISTEN (0A) whose inodes are among the process's descriptors.
fn listening_ports(pid: u32) -> Vec<u16> {
    let mut inodes = Vec::new();
    for fd in std::fs::read_dir(format!("/proc/{pid}/fd")).unwrap() {
        let link = std::fs::read_link(fd.unwrap().path()).unwrap_or_default();
        let link = link.to_string_lossy().into_owned();
        if let Some(inode) = link
            .strip_prefix("socket:[")
            .and_then(|r| r.strip_suffix(']'))
        {
            inodes.push(inode.to_owned());
        }
    }
    let mut ports = Vec::new();
    for table in ["/proc/net/tcp", "/proc/net/tcp6"] {
        let text = std::fs::read_to_string(table).unwrap_or_default();
        for row in text.lines().skip(1) {
            let f: Vec<&str> = row.split_whitespace().collect();
            if f.len() > 9 && f[3] == "0A" && inodes.iter().any(|i| i == f[9]) {
                let port = f[1].rsplit(':').next().unwrap();
                ports.push(u16::from_str_radix(port, 16).unwrap());
            }
        }
    }
    ports.sort();
    ports
}

#[test]
fn with_metrics_off_only_the_modbus_port_listens() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let cfg = Cfg::new(&socat.gw).serial("flow_control = \"none\"");
    let mut gw = Gateway::start(&cfg, dir.path());
    assert_eq!(
        listening_ports(gw.proc.pid()),
        [gw.addr.port()],
        "{}",
        gw.log()
    );
    assert!(!gw.log().contains("metrics on"), "{}", gw.log());
    gw.stop();
    // The same with the listener on: two ports, so the check above can see one.
    let cfg = cfg.metrics("listen = \"127.0.0.1:0\"");
    let mut gw = Gateway::start(&cfg, dir.path());
    let http = metrics_addr(&gw);
    let mut want = vec![gw.addr.port(), http.port()];
    want.sort();
    assert_eq!(listening_ports(gw.proc.pid()), want);
    gw.stop();
}

/// `mbgate status` summarises what the listener shows and its exit code says whether
/// the gateway is healthy: 0, then 1 once a unit stops answering; 3 when there is no
/// gateway to ask.
#[test]
fn status_prints_a_summary_and_its_exit_code_says_healthy_or_not() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let _dev = RawDevice::start(&socat.dev, register_device(&[1], Duration::ZERO));
    let cfg = Cfg::new(&socat.gw)
        .pty_line()
        .serial("flow_control = \"none\"")
        .metrics("listen = \"127.0.0.1:0\"");
    let mut gw = Gateway::start(&cfg, dir.path());
    let http = metrics_addr(&gw).to_string();
    let line = socat.gw.to_str().unwrap();
    let mut m = gw.connect();
    assert_eq!(
        transact(&mut m, &read_req(1, 1, 7, 1)),
        read_reply(1, 1, &[7])
    );
    let run = mbgate(&["status", "--metrics", &http]);
    assert_eq!(run.code, 0, "{}", run.stderr);
    let lines = run.lines();
    assert_eq!(lines[0], "healthy");
    assert!(
        lines[1].starts_with(&format!(
            "line {line}: port open, 1 masters, 1 requests, 1 replies, 0 timeouts, 0 backed off, 0 queued, 0 in flight, last reply "
        )),
        "{}",
        lines[1]
    );
    assert!(
        lines[2].starts_with("  unit 1: 1 requests, 1 replies, 0 timeouts, replies in "),
        "{}",
        lines[2]
    );
    assert_eq!(
        lines[3],
        format!(
            "listener {}: 1 masters, 1 connections, 0 refused, 0 protocol violations",
            gw.addr
        )
    );
    // Unit 2 has no device: three timeouts in a row.
    for tid in 2..5 {
        assert_eq!(transact(&mut m, &read_req(tid, 2, 7, 1))[7..], [0x83, 0x0B]);
    }
    let run = mbgate(&["status", "--metrics", &http]);
    assert_eq!(run.code, 1, "{}", run.stdout);
    assert_eq!(
        run.lines()[0],
        format!("NOT HEALTHY: unit 2 on {line} not answering")
    );
    assert!(
        run.stdout
            .contains("  unit 2: 3 requests, 0 replies, 3 timeouts, NOT ANSWERING\n"),
        "{}",
        run.stdout
    );
    gw.stop();
    // Nobody listens there any more.
    let run = mbgate(&["status", "--metrics", &http]);
    assert_eq!(run.code, 3);
    assert!(
        run.stderr
            .starts_with(&format!("mbgate: cannot ask the gateway at {http}: ")),
        "{}",
        run.stderr
    );
}

/// Every example configuration (config/examples/*.toml) run as it ships, its
/// addresses moved to free ports on 127.0.0.1 (an address two listeners share stays
/// shared) and its serial ports to paths where nothing is: one scrape of /metrics
/// prints each series (name and labels) once. A TCP and a UDP listener on one
/// address (dial-out.toml) are told apart by their `transport` label; printed twice
/// with the same labels, Prometheus keeps one and drops the other as a duplicate.
#[test]
fn every_example_configuration_prints_each_series_once() {
    let dir = tempdir();
    let mut examples: Vec<_> = std::fs::read_dir(repo().join("config/examples"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "toml"))
        .collect();
    examples.sort();
    assert!(examples.len() >= 8, "{examples:?}");
    let mut checked = Vec::new();
    for (n, example) in examples.iter().enumerate() {
        let name = example.file_name().unwrap().to_str().unwrap().to_owned();
        let text = local(&std::fs::read_to_string(example).unwrap(), dir.path(), n);
        let run = dir.path().join(format!("run{n}"));
        std::fs::create_dir_all(&run).unwrap();
        let file = run.join(&name);
        std::fs::write(&file, &text).unwrap();
        let gw = Proc::start(
            &["run", "--config", file.to_str().unwrap()],
            "metrics on http",
        );
        let http = gw.metrics_addr(Duration::from_secs(10));
        // The dials join the metrics once the gateway accepts masters.
        let dials = text.matches("[[dial]]").count();
        let mut body = String::new();
        wait_for(
            &format!("{name}: its dials on /metrics"),
            Duration::from_secs(10),
            || {
                body = get(http, "/metrics").1;
                body.matches("mbgate_listener_connections_total{listener=\"dial ")
                    .count()
                    == dials
            },
        );
        let mut seen = std::collections::BTreeMap::<&str, usize>::new();
        for line in body
            .lines()
            .filter(|l| !l.starts_with('#') && !l.is_empty())
        {
            let series = line.rsplit_once(' ').map_or(line, |(s, _)| s);
            *seen.entry(series).or_default() += 1;
        }
        let twice: Vec<_> = seen.iter().filter(|(_, n)| **n > 1).collect();
        assert!(
            twice.is_empty(),
            "{name}: series printed more than once: {twice:?}\n{text}\n{body}"
        );
        assert!(seen.len() > 20, "{name}: {body}");
        checked.push(name);
    }
    eprintln!("each series once: {checked:?}");
}

/// `text` (an example configuration) made to run here: every address on 0.0.0.0 or
/// 127.0.0.1 a free port of 127.0.0.1 (one address, one port), every `path` a file in
/// `dir` that does not exist, and the metrics listener on.
fn local(text: &str, dir: &std::path::Path, n: usize) -> String {
    let mut ports = std::collections::HashMap::<String, u16>::new();
    let mut out = String::new();
    let mut rest = text;
    while let Some(at) = rest.find('"') {
        out += &rest[..=at];
        rest = &rest[at + 1..];
        let end = rest.find('"').expect("a closing quote");
        let quoted = &rest[..end];
        let local = quoted
            .strip_prefix("0.0.0.0:")
            .or_else(|| quoted.strip_prefix("127.0.0.1:"))
            .filter(|p| p.parse::<u16>().is_ok());
        if local.is_some() {
            let port = *ports.entry(quoted.to_owned()).or_insert_with(free_port);
            out += &format!("127.0.0.1:{port}");
        } else if out.trim_end_matches('"').trim_end().ends_with("path =") {
            out += &dir
                .join(format!("absent{n}-{}", out.len()))
                .display()
                .to_string();
        } else {
            out += quoted;
        }
        out.push('"');
        rest = &rest[end + 1..];
    }
    out += rest;
    if !out.contains("[metrics]") {
        out += "\n[metrics]\nlisten = \"127.0.0.1:0\"\n";
    }
    out
}
