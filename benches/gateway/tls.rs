//! `tls`: what Modbus/TCP Security costs (docs/performance.md, docs/security.md): the
//! latency TLS adds to a transaction (FC 03 through a plain listener and through a TLS
//! listener of the same gateway, to the simulator on a TCP line, taking turns), and
//! full handshakes a second with an RSA-2048 client certificate carrying a role, one
//! after the other, with the gateway's CPU time for each. The masters are rustls
//! clients in this process; the certificates are made with the openssl CLI.

use super::common::pki::Pki;
use super::common::{cpu_ns, read_req, tempdir, Gateway, Launch};
use super::report::{command, diff_us, spread, us, Report};
use super::shared::{network_sim, samples, served, tcp_read};
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName};
use std::fmt::Write as _;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::sync::Arc;
use std::time::{Duration, Instant};

type Tls = rustls::StreamOwned<rustls::ClientConnection, TcpStream>;

fn client_config(pki: &Pki, who: &str) -> Arc<rustls::ClientConfig> {
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut roots = rustls::RootCertStore::empty();
    for c in CertificateDer::pem_file_iter(pki.pem("ca")).unwrap() {
        roots.add(c.unwrap()).unwrap();
    }
    let chain = CertificateDer::pem_file_iter(pki.pem(who))
        .unwrap()
        .map(Result::unwrap)
        .collect();
    let key = PrivateKeyDer::from_pem_file(pki.key(who)).unwrap();
    let config = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .unwrap()
        .with_root_certificates(roots)
        .with_client_auth_cert(chain, key)
        .unwrap();
    Arc::new(config)
}

/// A TLS master connected and through its handshake.
fn connect(config: &Arc<rustls::ClientConfig>, addr: &str) -> Tls {
    let sock = TcpStream::connect(addr).unwrap();
    sock.set_nodelay(true).unwrap();
    sock.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let name = ServerName::try_from("localhost").unwrap();
    let conn = rustls::ClientConnection::new(config.clone(), name).unwrap();
    let mut s = rustls::StreamOwned::new(conn, sock);
    while s.conn.is_handshaking() {
        s.conn.complete_io(&mut s.sock).expect("TLS handshake");
    }
    s
}

/// One FC 03 read of one register over TLS; how long it took.
fn read(s: &mut Tls, tid: u16) -> Duration {
    let req = read_req(tid, 1, 0, 1);
    let t = Instant::now();
    s.write_all(&req).unwrap();
    s.flush().unwrap();
    let mut head = [0u8; 6];
    s.read_exact(&mut head).unwrap();
    let mut rest = vec![0u8; usize::from(u16::from_be_bytes([head[4], head[5]]))];
    s.read_exact(&mut rest).unwrap();
    let took = t.elapsed();
    assert_eq!(
        (rest.len(), rest[1]),
        (5, 0x03),
        "not a normal reply: {rest:02X?}"
    );
    took
}

pub(super) fn tls(r: &mut Report) {
    eprintln!("tls: FC 03 through a plain and a TLS listener; TLS handshakes a second");
    const WARM: usize = 200;
    const N: usize = 2000;
    const ROUNDS: usize = 4;
    const HANDSHAKES: usize = 500;
    const HANDSHAKE_TIME: Duration = Duration::from_secs(5);
    let dir = tempdir();
    let pki = Pki::new(&dir.path().join("pki"));
    pki.master("operator-1", "ca", Some("operator"), 30);
    let (_sim, at) = network_sim();
    let text = format!(
        "[[line]]\n[line.tcp]\naddress = \"{at}\"\n\n[[listen]]\naddress = \"127.0.0.1:0\"\n\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\n{}\n\n[[role]]\nname = \"operator\"\n\n\
         [log]\nlevel = \"warn\"\n",
        pki.listen_tls("")
    );
    // The start-up lines are at info; the gateway logs at warn, so ask for its
    // addresses with info once, then run quiet.
    let mut gw = Gateway::launch_text(
        &text.replace("\"warn\"", "\"info\""),
        dir.path(),
        Launch::default(),
    );
    let tls_at = gw
        .log()
        .split("listening on ")
        .nth(2)
        .and_then(|rest| rest.split_whitespace().next())
        .expect("the TLS listener's address")
        .to_string();
    let plain_at = gw.addr.to_string();
    let config = client_config(&pki, "operator-1");
    let (mut plain, mut secure) = (vec![], vec![]);
    for _ in 0..ROUNDS {
        let mut s = served(&plain_at);
        plain.extend(samples(WARM, N / ROUNDS, |tid| tcp_read(&mut s, tid, 1)));
        drop(s);
        let mut s = connect(&config, &tls_at);
        secure.extend(samples(WARM, N / ROUNDS, |tid| read(&mut s, tid)));
    }
    // Handshakes, one after the other, each confirmed by a read (with TLS 1.3 the
    // client is through before the gateway has checked its certificate).
    let cpu_before = cpu_ns(gw.proc.pid());
    let start = Instant::now();
    let mut done = 0;
    while done < HANDSHAKES && start.elapsed() < HANDSHAKE_TIME {
        let mut s = connect(&config, &tls_at);
        read(&mut s, done as u16);
        done += 1;
    }
    let took = start.elapsed();
    let cpu = Duration::from_nanos(cpu_ns(gw.proc.pid()) - cpu_before);
    gw.terminate(Duration::from_secs(5));

    let (p, t) = (spread(&plain), spread(&secure));
    let mut table = String::from("| path | p50 | p99 | max |\n|---|---|---|---|\n");
    for (path, x) in [
        ("plain listener → mbgate → TCP → sim", &p),
        ("TLS 1.3 listener → mbgate → TCP → sim", &t),
    ] {
        let _ = writeln!(table, "| {path} | {} |", x.cells());
    }
    for (q, a, b) in [("p50", p.p50, t.p50), ("p99", p.p99, t.p99)] {
        let added = diff_us(a, b);
        let _ = writeln!(table, "| added by TLS, {q}: **{added:.0} µs** | | | |");
        r.row(
            "tls",
            &format!("TLS: added latency {q}, FC 03 × 1"),
            format!("{added:.0} µs ({} → {})", us(a), us(b)),
            "-",
            None,
        );
    }
    let rate = done as f64 / took.as_secs_f64();
    let each = cpu / done.max(1) as u32;
    let _ = writeln!(
        table,
        "\n{done} full handshakes (RSA 2048 server and client keys, TLS 1.3, client certificate with a role, no resumption), one after the other, each with one read: **{rate:.0} a second**, mbgate's CPU {:.2} ms each.",
        each.as_secs_f64() * 1e3
    );
    r.row(
        "tls",
        "TLS handshakes a second, one at a time (RSA 2048)",
        format!(
            "{rate:.0}/s; mbgate CPU {:.2} ms each",
            each.as_secs_f64() * 1e3
        ),
        "-",
        None,
    );
    r.detail(
        &format!("Modbus/TCP Security ({N} samples a path, in {ROUNDS} rounds, each after {WARM} warm-up; `mbgate sim --listen`, unpaced)"),
        &command("tls"),
        &table,
    );
}
