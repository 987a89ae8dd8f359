//! `mbgate status`'s work: asks a running gateway for its metrics, at its metrics
//! listener (`[metrics] listen`: over http, or https with a CA, a client certificate
//! and a user where its web configuration asks for them) or over its control socket
//! (`crate::gateway::control::status`), and makes a short summary per line, unit and
//! listener, and whether it is healthy (the flags and the exit code are
//! `crate::cli`'s).

use base64::Engine as _;
use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, SystemTime};

/// Why the gateway could not be asked.
#[derive(Debug, thiserror::Error)]
pub(crate) enum Unreachable {
    /// The address, the connection, or the exchange failed.
    #[error("{0}")]
    Io(#[from] std::io::Error),
    /// The address names no address.
    #[error("no address")]
    NoAddress,
    /// What answered did not speak HTTP.
    #[error("not an HTTP response")]
    NotHttp,
    /// It answered, but not with 200.
    #[error("{0} (is it mbgate's metrics listener?)")]
    Status(String),
    /// It asks for a user and password, and none were given.
    #[error("{0}: the metrics listener asks for a user and password: --user NAME, the password in MBGATE_PASSWORD or --password-file FILE (or, on the gateway's machine, `sudo mbgate status` asks over the control socket)")]
    Unauthorized(String),
    /// The user and password given were refused.
    #[error("{0}: the user or the password is wrong")]
    Refused(String),
    /// Too many logins from here lately.
    #[error("{0}")]
    TooMany(String),
    /// A CA, certificate or key file given for https.
    #[error("{0}")]
    Tls(#[from] crate::tls::TlsError),
    /// https without a CA to check the gateway against.
    #[error("https needs the CA that signed the gateway's certificate: --ca FILE")]
    NoCa,
    /// The TLS handshake failed.
    #[error("TLS: {0}")]
    Handshake(String),
}

/// Where `mbgate status` asks a gateway's metrics listener, and with what.
#[derive(Debug, Clone, Default)]
pub(crate) struct Asking {
    /// `ADDR`, `http://ADDR` or `https://ADDR`.
    pub(crate) url: String,
    /// https: the CA file the gateway's certificate must chain to.
    pub(crate) ca: Option<PathBuf>,
    /// https: a client certificate and its key.
    pub(crate) cert: Option<(PathBuf, PathBuf)>,
    /// A user and password.
    pub(crate) login: Option<(String, String)>,
}

/// The CA bundle of a Debian system, taken for https when no `--ca` is given.
pub(crate) const SYSTEM_CAS: &str = "/etc/ssl/certs/ca-certificates.crt";

/// How the gateway whose metrics listener `asking` names is: the report, and whether
/// it is healthy (every line open, every unit answering).
pub(crate) fn ask(asking: &Asking) -> Result<(String, bool), Unreachable> {
    let text = scrape(asking)?;
    Ok(summarize(&text))
}

/// The report of the metrics `text` (an exposition), and whether the gateway is
/// healthy.
pub(crate) fn summarize(text: &str) -> (String, bool) {
    summary(&parse(text), SystemTime::now())
}

/// What to do when nothing answers at `addr`: the metrics listener is off unless the
/// configuration gives it an address.
pub(crate) fn turn_on(addr: &str) -> String {
    format!(
        "mbgate: the gateway answers `mbgate status` on its metrics listener, which is off \
         unless its configuration names an address:\n\
         \n    [metrics]\n    listen = \"{addr}\"\n\n\
         then `systemctl reload` the service (or start `mbgate run` with --metrics-listen {addr}); \
         for a listener at another address, `mbgate status --metrics ADDR`; on the gateway's \
         machine, `sudo mbgate status --config FILE` asks over its control socket\n"
    )
}

/// The host of `host:port` (`[::1]:9502` gives `::1`).
fn host(address: &str) -> &str {
    let h = address.rsplit_once(':').map_or(address, |(h, _)| h);
    h.strip_prefix('[')
        .and_then(|h| h.strip_suffix(']'))
        .unwrap_or(h)
}

/// The client's TLS for `asking`, and the name the gateway's certificate must carry.
fn client_tls(asking: &Asking, addr: &str) -> Result<rustls::ClientConnection, Unreachable> {
    use crate::tls::{certificates, private_key, provider, roots, VERSIONS};
    let ca = match &asking.ca {
        Some(ca) => ca.clone(),
        None if std::path::Path::new(SYSTEM_CAS).exists() => PathBuf::from(SYSTEM_CAS),
        None => return Err(Unreachable::NoCa),
    };
    let roots = roots("--ca", &ca)?;
    let builder = rustls::ClientConfig::builder_with_provider(provider())
        .with_protocol_versions(VERSIONS)
        .expect("the ring provider speaks TLS 1.2 and 1.3")
        .with_root_certificates(roots);
    let mut config = match &asking.cert {
        Some((cert, key)) => {
            let chain = certificates("--cert", cert)?;
            let key = private_key("--key", key)?;
            builder
                .with_client_auth_cert(chain, key)
                .map_err(|e| Unreachable::Handshake(format!("--cert and --key: {e}")))?
        }
        None => builder.with_no_client_auth(),
    };
    config.alpn_protocols = vec![b"http/1.1".to_vec()];
    let name = rustls::pki_types::ServerName::try_from(host(addr).to_owned())
        .map_err(|_| Unreachable::NoAddress)?;
    rustls::ClientConnection::new(Arc::new(config), name)
        .map_err(|e| Unreachable::Handshake(e.to_string()))
}

/// GET /metrics as `asking` says, within a few seconds.
fn scrape(asking: &Asking) -> Result<String, Unreachable> {
    let within = Duration::from_secs(3);
    let url = asking.url.trim_end_matches('/');
    let (https, addr) = match url.split_once("://") {
        Some(("https", a)) => (true, a),
        Some(("http", a)) => (false, a),
        Some(_) => return Err(Unreachable::NoAddress),
        None => (false, url),
    };
    let to = addr
        .to_socket_addrs()?
        .next()
        .ok_or(Unreachable::NoAddress)?;
    let s = TcpStream::connect_timeout(&to, within)?;
    s.set_read_timeout(Some(within))?;
    let mut request = format!("GET /metrics HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    if let Some((user, password)) = &asking.login {
        let b = base64::engine::general_purpose::STANDARD.encode(format!("{user}:{password}"));
        request += &format!("Authorization: Basic {b}\r\n");
    }
    request += "\r\n";
    let all = if https {
        let mut tls = rustls::StreamOwned::new(client_tls(asking, addr)?, s);
        tls.write_all(request.as_bytes())
            .map_err(|e| Unreachable::Handshake(e.to_string()))?;
        let mut all = Vec::new();
        // A server that closes without TLS's close_notify ends the text all the same.
        match tls.read_to_end(&mut all) {
            Ok(_) => {}
            Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof && !all.is_empty() => {}
            Err(e) => return Err(Unreachable::Handshake(e.to_string())),
        }
        String::from_utf8_lossy(&all).into_owned()
    } else {
        let mut s = s;
        s.write_all(request.as_bytes())?;
        let mut all = String::new();
        s.read_to_string(&mut all)?;
        all
    };
    let (head, body) = all.split_once("\r\n\r\n").ok_or(Unreachable::NotHttp)?;
    let status = head.lines().next().unwrap_or("");
    if status.contains(" 401 ") && asking.login.is_some() {
        return Err(Unreachable::Refused(status.to_owned()));
    }
    if status.contains(" 401 ") {
        return Err(Unreachable::Unauthorized(status.to_owned()));
    }
    if status.contains(" 429 ") {
        return Err(Unreachable::TooMany(format!("{status}: {}", body.trim())));
    }
    if !status.contains(" 200 ") {
        return Err(Unreachable::Status(status.to_owned()));
    }
    Ok(body.to_owned())
}

/// Samples by name, each with its labels.
type Samples = BTreeMap<String, Vec<(BTreeMap<String, String>, f64)>>;

/// The samples of an exposition (comments skipped).
fn parse(text: &str) -> Samples {
    let mut out = Samples::new();
    for line in text
        .lines()
        .filter(|l| !l.starts_with('#') && !l.is_empty())
    {
        let Some((series, value)) = line.rsplit_once(' ') else {
            continue;
        };
        let Ok(value) = value.parse::<f64>() else {
            continue;
        };
        let (name, labels) = match series.split_once('{') {
            Some((name, rest)) => (name, labels(rest.strip_suffix('}').unwrap_or(rest))),
            None => (series, BTreeMap::new()),
        };
        out.entry(name.to_owned())
            .or_default()
            .push((labels, value));
    }
    out
}

/// `a="x",b="y \"q\""` → {a: x, b: y "q"}.
fn labels(s: &str) -> BTreeMap<String, String> {
    let mut out = BTreeMap::new();
    let mut chars = s.chars().peekable();
    loop {
        let key: String = chars.by_ref().take_while(|c| *c != '=').collect();
        if key.is_empty() || chars.next() != Some('"') {
            break;
        }
        let mut value = String::new();
        while let Some(c) = chars.next() {
            match c {
                '\\' => match chars.next() {
                    Some('n') => value.push('\n'),
                    Some(c) => value.push(c),
                    None => break,
                },
                '"' => break,
                c => value.push(c),
            }
        }
        out.insert(key.trim_start_matches(',').to_owned(), value);
        if chars.peek() == Some(&',') {
            chars.next();
        }
    }
    out
}

/// The value of `name` whose labels include all of `with`.
fn get(s: &Samples, name: &str, with: &[(&str, &str)]) -> f64 {
    let Some(all) = s.get(name) else {
        return 0.0;
    };
    all.iter()
        .find(|(l, _)| {
            with.iter()
                .all(|(k, v)| l.get(*k).map(String::as_str) == Some(*v))
        })
        .map_or(0.0, |(_, v)| *v)
}

/// Each listener once, with its transport (`tcp`, `udp`; none from a gateway older
/// than the label), in order: a TCP and a UDP listener on one address are two.
fn listeners(s: &Samples) -> Vec<(String, Option<String>)> {
    let mut seen = Vec::new();
    for (l, _) in s
        .get("mbgate_listener_connections_total")
        .into_iter()
        .flatten()
    {
        if let Some(name) = l.get("listener") {
            let one = (name.clone(), l.get("transport").cloned());
            if !seen.contains(&one) {
                seen.push(one);
            }
        }
    }
    seen
}

/// Each distinct value of label `key` among the samples of `name`, in order.
fn values_of(s: &Samples, name: &str, key: &str) -> Vec<String> {
    let mut seen: Vec<String> = Vec::new();
    for (l, _) in s.get(name).into_iter().flatten() {
        if let Some(v) = l.get(key) {
            if !seen.contains(v) {
                seen.push(v.clone());
            }
        }
    }
    seen
}

fn n(v: f64) -> String {
    format!("{}", v as u64)
}

/// The masters connected to `listener`, one line each: address, connection, for how
/// long, and on a TLS listener the role and certificate subject.
fn masters(s: &Samples, listener: &str, unix: f64) -> String {
    let mut out = String::new();
    let all = s
        .get("mbgate_master_connected_timestamp_seconds")
        .into_iter()
        .flatten();
    for (lb, since) in
        all.filter(|(lb, _)| lb.get("listener").map(String::as_str) == Some(listener))
    {
        let label = |k: &str| lb.get(k).cloned().unwrap_or_default();
        let who = match label("role").as_str() {
            "" => "plain TCP".to_owned(),
            role => format!("role {role}, {}", label("subject")),
        };
        out += &format!(
            "  master {} (conn {}): {who}, connected {:.0} s\n",
            label("peer"),
            label("conn"),
            (unix - since).max(0.0)
        );
    }
    out
}

/// The report, and whether every line is open and every unit answering.
fn summary(s: &Samples, now: SystemTime) -> (String, bool) {
    let mut out = String::new();
    let mut problems = Vec::new();
    let unix = now
        .duration_since(SystemTime::UNIX_EPOCH)
        .unwrap_or_default()
        .as_secs_f64();
    for line in values_of(s, "mbgate_line_requests_total", "line") {
        out += &line_summary(s, &line, unix, &mut problems);
        out += &units_summary(s, &line, &mut problems);
    }
    let mut listed = Vec::new();
    for (listener, transport) in listeners(s) {
        out += &listener_summary(s, &listener, transport.as_deref());
        // The masters carry the address, not the transport: listed once.
        if !listed.contains(&listener) {
            out += &masters(s, &listener, unix);
            listed.push(listener);
        }
    }
    let healthy = problems.is_empty();
    let head = if healthy {
        "healthy".to_owned()
    } else {
        format!("NOT HEALTHY: {}", problems.join("; "))
    };
    (format!("{head}\n{out}"), healthy)
}

/// A line's row: its port, its counts, its last reply; a port not open is a problem.
fn line_summary(s: &Samples, line: &str, unix: f64, problems: &mut Vec<String>) -> String {
    let mut out = String::new();
    let l = [("line", line)];
    let open = get(s, "mbgate_line_port_open", &l) == 1.0;
    if !open {
        problems.push(format!("{line} not open"));
    }
    let last = match s
        .get("mbgate_line_last_reply_timestamp_seconds")
        .and_then(|all| {
            all.iter()
                .find(|(lb, _)| lb.get("line").is_some_and(|l| l == line))
        }) {
        Some((_, at)) => format!("last reply {:.1} s ago", (unix - at).max(0.0)),
        None => "no reply yet".into(),
    };
    out += &format!(
        "line {line}: port {}, {} masters, {} requests, {} replies, {} timeouts, {} backed off, {} queued, {} in flight, {last}\n",
        if open { "open" } else { "NOT OPEN" },
        n(get(s, "mbgate_line_masters", &l)),
        n(get(s, "mbgate_line_requests_total", &l)),
        n(get(s, "mbgate_line_replies_total", &l)),
        n(get(s, "mbgate_line_timeouts_total", &l)),
        // Answered 0x0B at once, their unit backed off: neither a reply nor a
        // timeout on the line.
        n(get(s, "mbgate_line_backed_off_requests_total", &l)),
        n(get(s, "mbgate_line_queued", &l)),
        n(get(s, "mbgate_line_in_flight", &l)),
    );
    out
}

/// The rows of a line's units; a unit not answering is a problem.
fn units_summary(s: &Samples, line: &str, problems: &mut Vec<String>) -> String {
    let mut out = String::new();
    let units = s.get("mbgate_unit_requests_total").into_iter().flatten();
    let units = units.filter(|(lb, _)| lb.get("line").is_some_and(|l| l == line));
    for (lb, requests) in units {
        let unit = lb.get("unit").cloned().unwrap_or_default();
        let u = [("line", line), ("unit", unit.as_str())];
        let count = get(s, "mbgate_unit_reply_seconds_count", &u);
        let avg = if count > 0.0 {
            format!(
                ", replies in {:.1} ms on average",
                1000.0 * get(s, "mbgate_unit_reply_seconds_sum", &u) / count
            )
        } else {
            String::new()
        };
        let mut state = String::new();
        if get(s, "mbgate_unit_not_answering", &u) == 1.0 {
            state += ", NOT ANSWERING";
            problems.push(format!("unit {unit} on {line} not answering"));
        }
        if get(s, "mbgate_unit_backed_off", &u) == 1.0 {
            state += ", backed off";
        }
        let learned = s
            .get("mbgate_unit_response_timeout_seconds")
            .and_then(|all| {
                all.iter().find(|(lb, _)| {
                    lb.get("line").is_some_and(|l| l == line) && lb.get("unit") == Some(&unit)
                })
            });
        if let Some((lb, t)) = learned {
            let why = lb.get("why").map_or("", String::as_str);
            state += &format!(", timeout {:.1} ms learned ({why})", t * 1000.0);
        }
        out += &format!(
            "  unit {unit}: {} requests, {} replies, {} timeouts{avg}{state}\n",
            n(*requests),
            n(get(s, "mbgate_unit_replies_total", &u)),
            n(get(s, "mbgate_unit_timeouts_total", &u)),
        );
    }
    out
}

/// A listener's rows: its counts and what its access rules refused.
fn listener_summary(s: &Samples, listener: &str, transport: Option<&str>) -> String {
    let mut out = String::new();
    // A gateway older than the `transport` label has none.
    let mut l = vec![("listener", listener)];
    let said = match transport {
        Some(t) => {
            l.push(("transport", t));
            if t == "tcp" {
                String::new()
            } else {
                format!(" ({})", t.to_uppercase())
            }
        }
        None => String::new(),
    };
    out += &format!(
        "listener {listener}{said}: {} masters, {} connections, {} refused, {} protocol violations\n",
        n(get(s, "mbgate_listener_masters", &l)),
        n(get(s, "mbgate_listener_connections_total", &l)),
        n(get(s, "mbgate_listener_refused_connections_total", &l)),
        n(get(s, "mbgate_listener_protocol_violations_total", &l)),
    );
    let access = [
        (
            "mbgate_listener_denied_connections_total",
            "not in the allow list",
        ),
        ("mbgate_listener_tls_failed_total", "TLS handshakes failed"),
        (
            "mbgate_listener_tls_refused_total",
            "TLS masters refused for their role",
        ),
        ("mbgate_listener_denied_requests_total", "requests denied"),
    ];
    let said: Vec<String> = access
        .iter()
        .map(|(name, what)| (get(s, name, &l), what))
        .filter(|(v, _)| *v > 0.0)
        .map(|(v, what)| format!("{} {what}", n(v)))
        .collect();
    if !said.is_empty() {
        out += &format!("  {}\n", said.join(", "));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn labels_with_escapes() {
        let l = labels(r#"line="/dev/a \"b\"",unit="1""#);
        assert_eq!(l["line"], "/dev/a \"b\"");
        assert_eq!(l["unit"], "1");
    }

    /// A TCP and a UDP listener on one address: two lines, the UDP one said so; a
    /// gateway older than the `transport` label still gets its line.
    #[test]
    fn listeners_on_one_address_by_transport() {
        let text = "\
mbgate_listener_connections_total{listener=\"127.0.0.1:5502\",transport=\"tcp\"} 3
mbgate_listener_masters{listener=\"127.0.0.1:5502\",transport=\"tcp\"} 1
mbgate_listener_connections_total{listener=\"127.0.0.1:5502\",transport=\"udp\"} 2
mbgate_listener_masters{listener=\"127.0.0.1:5502\",transport=\"udp\"} 2
";
        let (report, _) = summary(&parse(text), SystemTime::now());
        assert_eq!(
            report,
            "healthy\n\
             listener 127.0.0.1:5502: 1 masters, 3 connections, 0 refused, 0 protocol violations\n\
             listener 127.0.0.1:5502 (UDP): 2 masters, 2 connections, 0 refused, 0 protocol violations\n"
        );
        let old = "mbgate_listener_connections_total{listener=\"0.0.0.0:502\"} 4\n";
        let (report, _) = summary(&parse(old), SystemTime::now());
        assert!(
            report.ends_with("listener 0.0.0.0:502: 0 masters, 4 connections, 0 refused, 0 protocol violations\n"),
            "{report}"
        );
    }

    #[test]
    fn a_unit_not_answering_or_a_closed_port_is_not_healthy() {
        let text = "\
mbgate_line_requests_total{line=\"/dev/x\"} 5
mbgate_line_port_open{line=\"/dev/x\"} 1
mbgate_unit_requests_total{line=\"/dev/x\",unit=\"1\"} 5
mbgate_unit_not_answering{line=\"/dev/x\",unit=\"1\"} 0
";
        let (report, healthy) = summary(&parse(text), SystemTime::now());
        assert!(healthy, "{report}");
        assert!(
            report.starts_with("healthy\nline /dev/x: port open"),
            "{report}"
        );
        let sick = text.replace(
            "not_answering{line=\"/dev/x\",unit=\"1\"} 0",
            "not_answering{line=\"/dev/x\",unit=\"1\"} 1",
        );
        let (report, healthy) = summary(&parse(&sick), SystemTime::now());
        assert!(!healthy);
        assert!(
            report.starts_with("NOT HEALTHY: unit 1 on /dev/x not answering\n"),
            "{report}"
        );
        let closed = text.replace(
            "port_open{line=\"/dev/x\"} 1",
            "port_open{line=\"/dev/x\"} 0",
        );
        let (report, healthy) = summary(&parse(&closed), SystemTime::now());
        assert!(!healthy);
        assert!(
            report.starts_with("NOT HEALTHY: /dev/x not open\n"),
            "{report}"
        );
    }
}
