//! The gateway benchmarks: added latency, wire efficiency, fairness and
//! footprint, measured side by side in one run against the device simulator on socat
//! pty pairs, and printed as Markdown.
//!
//! `cargo bench --bench gateway [-- SCENARIO...]`, SCENARIO one of `latency`, `wire`,
//! `fairness`, `footprint`, `rtu`, `rtu-backoff`, `rtu-limit`, `coalesce`, `tcp-line`,
//! `rtu-listener`, `metrics`, `tls` (all when none is named). `rtu-limit` compares with mbusd
//! given `MBUSD=/path/to/mbusd`; `MBGATE_BENCH_BASELINE=PATH` names another mbgate
//! build (e.g. the commit before a change) that `coalesce` measures beside this one.
//! `scripts/bench` runs this and
//! `benches/decoder.rs` and writes the tables into docs/performance.md. With
//! `MBGATE_BENCH_MD=FILE` the tables are also written to FILE.
//!
//! Everything listens on 127.0.0.1 port 0; every load loop is bounded in count and
//! time. The masters run in this process (blocking sockets, one thread each); the
//! gateway (`mbgate run`) and the simulator (`mbgate sim`) are the release binaries.

#[path = "../tests/common/mod.rs"]
mod common;
#[path = "gateway/tls.rs"]
mod tls;

use common::sim::RawLine;
use common::{
    cpu_ns, read_frame, read_reply, read_req, tempdir, wait_for, write_req, Cfg, Gateway, Launch,
    Proc, Py, Socat,
};
use std::fmt::Write as _;
use std::io::Write as _;
use std::net::TcpStream;
use std::path::Path;
use std::process::Command;
use std::sync::atomic::{AtomicU16, Ordering};
use std::sync::{Arc, Barrier};
use std::thread;
use std::time::{Duration, Instant};

/// Request bytes of an FC 03 read (MBAP): header 7 + function, address, quantity.
const REQ: usize = 12;

/// Reply bytes of an FC 03 read of `qty` registers (MBAP).
fn reply_len(qty: u16) -> usize {
    9 + 2 * usize::from(qty)
}

/// Upper bound on transactions in any one load loop, whatever its time budget.
const MAX_TRANSACTIONS: usize = 200_000;

/// A benchmark scenario: it measures, and adds its rows and tables to the report.
type Scenario = fn(&mut Report);

fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    // Each scenario by the name that picks it, in the order they run.
    let all: [(&str, Scenario); 13] = [
        ("latency", latency),
        ("wire", wire),
        ("fairness", fairness),
        ("footprint", footprint),
        ("rtu", rtu),
        ("rtu-backoff", rtu_backoff),
        ("rtu-limit", rtu_limit),
        ("coalesce", coalesce),
        ("tcp-line", tcp_line),
        ("rtu-listener", rtu_listener),
        ("metrics", metrics_cost),
        ("tls", tls::tls),
        ("capture", capture_cost),
    ];
    let names: Vec<&str> = all.iter().map(|(name, _)| *name).collect();
    if let Some(bad) = args.iter().find(|a| !names.contains(&a.as_str())) {
        eprintln!("unknown scenario {bad:?}; scenarios: {}", names.join(", "));
        std::process::exit(2);
    }
    let wanted = |s: &str| args.is_empty() || args.iter().any(|a| a == s);
    let mut r = Report::default();
    let load_before = loadavg();
    for (name, scenario) in all {
        if wanted(name) {
            scenario(&mut r);
        }
    }
    let md = r.render(&load_before, &loadavg());
    println!("{md}");
    if let Some(path) = std::env::var_os("MBGATE_BENCH_MD") {
        std::fs::write(&path, &md).expect("write MBGATE_BENCH_MD");
    }
}

// ---------------------------------------------------------------------------------
// The report

#[derive(Default)]
struct Report {
    rows: Vec<Row>,
    details: String,
}

struct Row {
    measure: String,
    figure: String,
    target: String,
    met: Option<bool>,
    scenario: &'static str,
}

impl Report {
    fn row(
        &mut self,
        scenario: &'static str,
        measure: &str,
        figure: String,
        target: &str,
        met: Option<bool>,
    ) {
        eprintln!("  {measure}: {figure} (target {target})");
        self.rows.push(Row {
            measure: measure.into(),
            figure,
            target: target.into(),
            met,
            scenario,
        });
    }

    fn detail(&mut self, title: &str, command: &str, table: &str) {
        let _ = write!(self.details, "#### {title}\n\n`{command}`\n\n{table}\n");
    }

    fn render(&self, load_before: &str, load_after: &str) -> String {
        let mut s = String::new();
        let _ = writeln!(
            s,
            "Load average (1, 5, 15 min) at start: {load_before}; at end: {load_after}.\n"
        );
        s += "| measure | figure | target | met | command |\n|---|---|---|---|---|\n";
        for r in &self.rows {
            let met = match r.met {
                Some(true) => "yes",
                Some(false) => "**no**",
                None => "-",
            };
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | `{}` |",
                r.measure,
                r.figure,
                r.target,
                met,
                command(r.scenario)
            );
        }
        s += "\n";
        s += &self.details;
        s
    }
}

fn command(scenario: &str) -> String {
    format!("cargo bench --bench gateway -- {scenario}")
}

fn loadavg() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|l| l.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "?".into())
}

fn us(d: Duration) -> String {
    format!("{:.1} µs", d.as_secs_f64() * 1e6)
}

fn ms(d: Duration) -> String {
    format!("{:.2} ms", d.as_secs_f64() * 1e3)
}

fn pct(x: f64) -> String {
    format!("{:.1} %", x * 100.0)
}

/// p50, p99 and max of some durations.
#[derive(Clone, Copy)]
struct Spread {
    p50: Duration,
    p99: Duration,
    max: Duration,
}

fn spread(samples: &[Duration]) -> Spread {
    assert!(!samples.is_empty(), "no samples");
    let mut v = samples.to_vec();
    v.sort();
    let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
    Spread {
        p50: at(0.50),
        p99: at(0.99),
        max: v[v.len() - 1],
    }
}

/// The signed difference b - a, in µs.
fn diff_us(a: Duration, b: Duration) -> f64 {
    (b.as_secs_f64() - a.as_secs_f64()) * 1e6
}

// ---------------------------------------------------------------------------------
// Peers

/// A pty pair and a quiet simulator on its device end: no per-packet log, started
/// once it answers a read from the gateway's end.
struct Line {
    dir: tempfile::TempDir,
    socat: Socat,
    _sim: Device,
}

/// The device on a line's far end; stopped when the line drops.
enum Device {
    Sim(#[allow(dead_code)] Proc),
    Pymodbus(#[allow(dead_code)] Py),
}

impl Line {
    fn start(sim_args: &[&str]) -> Line {
        Line::start_probed(sim_args, &read_req(1, 1, 0, 1), reply_len(1))
    }

    /// [`Line::start`], the simulator probed with `probe`, answered in `answer` bytes.
    fn start_probed(sim_args: &[&str], probe_req: &[u8], answer: usize) -> Line {
        Line::probed(
            |dev| {
                let mut args = vec!["sim", "--serial", dev];
                args.extend(["--profile", "generic", "--log-level", "warn"]);
                args.extend_from_slice(sim_args);
                // No log line to wait for ("" is there at once): the probe decides.
                Device::Sim(Proc::start(&args, ""))
            },
            probe_req,
            answer,
        )
    }

    /// pymodbus' own RTU server (tests/py/stock_server.py, `ModbusSerialServer` with the
    /// RTU framer) on a pty pair of its own: a device that answers as fast as Python
    /// does, nothing paced.
    fn pymodbus_rtu(baud: u32) -> Line {
        let speed = baud.to_string();
        Line::probed(
            |dev| {
                let args = ["--port", dev, "--framer", "rtu", "--baud", &speed];
                Device::Pymodbus(Py::start("stock_server.py", &args))
            },
            &serial_read("rtu", 1),
            serial_reply_len("rtu", 1),
        )
    }

    /// A pty pair with the device `start` puts on its far end (given that end's path),
    /// once it answers `probe_req` in `answer` bytes.
    fn probed(start: impl FnOnce(&str) -> Device, probe_req: &[u8], answer: usize) -> Line {
        let dir = tempdir();
        let socat = Socat::start(dir.path());
        let device = start(socat.dev.to_str().unwrap());
        let mut probe = RawLine::open(&socat.gw);
        let since = Instant::now();
        while probe.transact(probe_req, answer).len() < answer {
            assert!(
                since.elapsed() < Duration::from_secs(20),
                "the device never answered"
            );
        }
        Line {
            dir,
            socat,
            _sim: device,
        }
    }

    fn raw(&self) -> RawLine {
        RawLine::open(&self.socat.gw)
    }

    /// `mbgate run` on this line: log at info, and the given `[relay]`/`[tcp]` lines.
    /// A pty has no USB adapter's latency: a lone MBAP reply is confirmed after 3.5
    /// character times, not the default `silence_floor_ms`.
    fn gateway(&self, relay: &[&str], tcp: &[&str]) -> Gateway {
        let cfg = Cfg::new(&self.socat.gw).serial("silence_floor_ms = 0");
        self.gateway_with(cfg, relay, tcp)
    }

    /// [`Line::gateway`] from a configuration with `[serial]` lines of its own.
    fn gateway_with(&self, cfg: Cfg, relay: &[&str], tcp: &[&str]) -> Gateway {
        let mut cfg = cfg.log_level("info");
        for l in relay {
            cfg = cfg.relay(l);
        }
        for l in tcp {
            cfg = cfg.tcp(l);
        }
        Gateway::start(&cfg, self.dir.path())
    }
}

fn connect(gw: &Gateway) -> TcpStream {
    let s = gw.connect();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    s
}

/// One FC 03 round trip through the gateway; panics unless it is the normal reply.
fn tcp_read(s: &mut TcpStream, tid: u16, qty: u16) -> Duration {
    let req = read_req(tid, 1, 0, qty);
    let t = Instant::now();
    s.write_all(&req).expect("send");
    let reply = read_frame(s);
    let took = t.elapsed();
    assert_eq!(
        (reply.len(), reply[7]),
        (reply_len(qty), 0x03),
        "not a normal reply: {reply:02X?}"
    );
    took
}

/// One FC 03 round trip straight to the simulator on the pty.
fn raw_read(m: &mut RawLine, tid: u16, qty: u16) -> Duration {
    let req = read_req(tid, 1, 0, qty);
    let t = Instant::now();
    let reply = m.transact(&req, reply_len(qty));
    let took = t.elapsed();
    assert_eq!(reply.len(), reply_len(qty), "short reply: {reply:02X?}");
    took
}

/// Runs `f` `n` times after `warm` unrecorded runs.
fn samples(warm: usize, n: usize, mut f: impl FnMut(u16) -> Duration) -> Vec<Duration> {
    for i in 0..warm {
        f(i as u16);
    }
    (0..n).map(|i| f(i as u16)).collect()
}

// ---------------------------------------------------------------------------------
// 1. Added latency

/// The pause that confirms a lone MBAP reply at the gateway's 19 200 baud with
/// `silence_floor_ms = 0`: 3.5 characters of 10 bits, as the relay reckons it
/// (docs/reliability.md, "How", item 2).
fn pause() -> Duration {
    Duration::from_micros(mbgate::frame::rtu::t35_us(19_200, 10))
}

fn latency(r: &mut Report) {
    eprintln!("latency: FC 03 straight to the simulator, then through mbgate");
    const WARM: usize = 200;
    const N: usize = 2000;
    // The three paths take turns, ROUNDS times, so a change in the machine's load
    // during the run falls on all of them alike.
    const ROUNDS: usize = 4;
    let line = Line::start(&[]);
    let (mut direct, mut piped, mut through) = (vec![vec![]; 2], vec![vec![]; 2], vec![vec![]; 2]);
    let (mut cpu, mut transactions) = (0, 0);
    for _ in 0..ROUNDS {
        let mut m = line.raw();
        for (i, qty) in [1, 10].into_iter().enumerate() {
            direct[i].extend(samples(WARM, N / ROUNDS, |tid| raw_read(&mut m, tid, qty)));
        }
        drop(m);
        let (mut pipe, addr) = socat_pipe(&line.socat.gw);
        let mut s = TcpStream::connect(addr).expect("connect to socat");
        s.set_nodelay(true).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        for (i, qty) in [1, 10].into_iter().enumerate() {
            piped[i].extend(samples(WARM, N / ROUNDS, |tid| tcp_read(&mut s, tid, qty)));
        }
        let _ = pipe.kill();
        let _ = pipe.wait();
        let mut gw = line.gateway(&[], &[]);
        let mut s = connect(&gw);
        let cpu0 = cpu_ns(gw.proc.pid());
        for (i, qty) in [1, 10].into_iter().enumerate() {
            through[i].extend(samples(WARM, N / ROUNDS, |tid| tcp_read(&mut s, tid, qty)));
        }
        cpu += cpu_ns(gw.proc.pid()) - cpu0;
        transactions += 2 * (WARM + N / ROUNDS);
        gw.terminate(Duration::from_secs(5));
    }
    // What mbgate itself spends on a transaction, against what it adds to one.
    let per = Duration::from_nanos(cpu) / transactions as u32;
    r.row(
        "latency",
        "mbgate CPU time per transaction (schedstat)",
        us(per),
        "(reported)",
        None,
    );
    let mut t = String::from("| registers | path | p50 | p99 | max |\n|---|---|---|---|---|\n");
    for (i, qty) in [1u16, 10].into_iter().enumerate() {
        let (d, p, g) = (spread(&direct[i]), spread(&piped[i]), spread(&through[i]));
        for (path, x) in [
            ("pty → sim (direct)", d),
            ("TCP → socat (a bare byte pipe) → pty → sim", p),
            ("TCP → mbgate → pty → sim", g),
        ] {
            let _ = writeln!(
                t,
                "| {qty} | {path} | {} | {} | {} |",
                us(x.p50),
                us(x.p99),
                us(x.max)
            );
        }
        let (a50, a99) = (diff_us(d.p50, g.p50), diff_us(d.p99, g.p99));
        let _ = writeln!(
            t,
            "| {qty} | added by the byte pipe | {:.0} µs | {:.0} µs | |",
            diff_us(d.p50, p.p50),
            diff_us(d.p99, p.p99)
        );
        let _ = writeln!(
            t,
            "| {qty} | **added by mbgate** (of which a lone reply's confirmation pause: {}) | **{a50:.0} µs** | **{a99:.0} µs** | |",
            us(pause()),
        );
        for (q, added, before, after, target) in [
            ("p50", a50, d.p50, g.p50, 50.0),
            ("p99", a99, d.p99, g.p99, 150.0),
        ] {
            r.row(
                "latency",
                &format!("added latency {q}, FC 03 × {qty}"),
                format!("{added:.0} µs ({} → {})", us(before), us(after)),
                &format!("≤ {target:.0} µs"),
                Some(added <= target),
            );
        }
        r.row(
            "latency",
            &format!("added latency p50, FC 03 × {qty}, less the confirmation pause"),
            format!("{:.0} µs", a50 - pause().as_secs_f64() * 1e6),
            "(reported)",
            None,
        );
    }
    r.detail(
        &format!("Added latency ({N} samples a path and size, in {ROUNDS} rounds in which the paths take turns, each after {WARM} warm-up; simulator unpaced, no delay; every path crosses the one socat hop of the pty pair)"),
        &command("latency"),
        &t,
    );
}

/// GET `path` from `addr`, the whole answer.
fn http_get(addr: &str, path: &str) -> usize {
    use std::io::Read as _;
    let Ok(mut s) = TcpStream::connect(addr) else {
        return 0;
    };
    let _ = write!(s, "GET {path} HTTP/1.1\r\n\r\n");
    let mut all = Vec::new();
    let _ = s.read_to_end(&mut all);
    all.len()
}

/// CPU time of the process's main thread (the runtime the relay runs on), in ns.
fn main_thread_cpu_ns(pid: u32) -> u64 {
    let s =
        std::fs::read_to_string(format!("/proc/{pid}/task/{pid}/schedstat")).unwrap_or_default();
    s.split_whitespace()
        .next()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0)
}

/// What the metrics cost: one master polling FC 03 × 1 through the gateway with
/// `[metrics]` off; on, /metrics scraped every second; on, /metrics and the status
/// page's /status.json every second (frames recorded: the worst case). In rounds that
/// take turns; CPU per transaction (the whole process, and the relay's thread alone)
/// and round trips, each against off. The counters themselves are kept in every case.
fn metrics_cost(r: &mut Report) {
    eprintln!("metrics: the same polling with the metrics listener off and on");
    const WARM: usize = 200;
    const N: usize = 4000;
    const ROUNDS: usize = 4;
    const CASES: [(&str, bool, bool); 3] = [
        ("off", false, false),
        ("on, /metrics scraped every second", true, false),
        ("on, /metrics and the status page every second", true, true),
    ];
    let line = Line::start(&[]);
    let mut lat = vec![Vec::new(); CASES.len()];
    let mut cpu = [0u64; CASES.len()];
    let mut relay_cpu = [0u64; CASES.len()];
    let mut transactions = [0usize; CASES.len()];
    for _ in 0..ROUNDS {
        for (i, (_, on, page)) in CASES.into_iter().enumerate() {
            let mut cfg = Cfg::new(&line.socat.gw).serial("silence_floor_ms = 0");
            if on {
                cfg = cfg.metrics("listen = \"127.0.0.1:0\"");
            }
            let mut gw = line.gateway_with(cfg, &[], &[]);
            let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
            let scraper = on.then(|| {
                gw.wait_log("metrics on http://", Duration::from_secs(5));
                let log = gw.log();
                let rest = log.split("metrics on http://").nth(1).unwrap();
                let addr = rest.split('/').next().unwrap().to_owned();
                let stop = stop.clone();
                thread::spawn(move || {
                    while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                        assert!(http_get(&addr, "/metrics") > 1000);
                        if page {
                            assert!(http_get(&addr, "/status.json") > 100);
                        }
                        thread::sleep(Duration::from_secs(1));
                    }
                })
            });
            let mut s = connect(&gw);
            let pid = gw.proc.pid();
            let (cpu0, relay0) = (cpu_ns(pid), main_thread_cpu_ns(pid));
            lat[i].extend(samples(WARM, N / ROUNDS, |tid| tcp_read(&mut s, tid, 1)));
            cpu[i] += cpu_ns(pid) - cpu0;
            relay_cpu[i] += main_thread_cpu_ns(pid) - relay0;
            transactions[i] += WARM + N / ROUNDS;
            stop.store(true, std::sync::atomic::Ordering::Relaxed);
            if let Some(t) = scraper {
                t.join().expect("the scraper");
            }
            gw.terminate(Duration::from_secs(5));
        }
    }
    let per = |v: &[u64], i: usize| Duration::from_nanos(v[i]) / transactions[i] as u32;
    let mut t = String::from(
        "| metrics | CPU per transaction (process) | relay's thread | p50 | p99 | max |\n|---|---|---|---|---|---|\n",
    );
    for (i, (name, _, _)) in CASES.into_iter().enumerate() {
        let x = spread(&lat[i]);
        let _ = writeln!(
            t,
            "| {name} | {} | {} | {} | {} | {} |",
            us(per(&cpu, i)),
            us(per(&relay_cpu, i)),
            us(x.p50),
            us(x.p99),
            us(x.max)
        );
    }
    let off = spread(&lat[0]);
    for (i, (name, _, _)) in CASES.into_iter().enumerate().skip(1) {
        let pct = |a: f64, b: f64| (b / a - 1.0) * 100.0;
        let (a, b) = (per(&cpu, 0), per(&cpu, i));
        let cpu_pct = pct(a.as_secs_f64(), b.as_secs_f64());
        r.row(
            "metrics",
            &format!("metrics {name}: CPU per transaction against off"),
            format!("{cpu_pct:+.1} % ({} → {})", us(a), us(b)),
            "< 5 %",
            Some(cpu_pct < 5.0),
        );
        let x = spread(&lat[i]);
        for (q, a, b) in [("p50", off.p50, x.p50), ("p99", off.p99, x.p99)] {
            let p = pct(a.as_secs_f64(), b.as_secs_f64());
            r.row(
                "metrics",
                &format!("metrics {name}: round trip {q} against off, FC 03 × 1"),
                format!("{p:+.1} % ({} → {})", us(a), us(b)),
                "< 5 %",
                Some(p < 5.0),
            );
        }
    }
    r.detail(
        &format!("The metrics' cost ({N} samples a case, in {ROUNDS} rounds taking turns, each after {WARM} warm-up)"),
        &command("metrics"),
        &t,
    );
}

/// `socat TCP-LISTEN:0 FILE:PTY`: the least any TCP-to-serial process can add (a
/// byte pipe, no framing), as a second baseline. Returns it and its address.
fn socat_pipe(pty: &Path) -> (std::process::Child, std::net::SocketAddr) {
    socat_to(&format!("FILE:{},raw,echo=0", pty.display()))
}

/// `socat TCP-LISTEN:0 FAR`: a bare byte pipe to `FAR` (a pty, a TCP address).
fn socat_to(far: &str) -> (std::process::Child, std::net::SocketAddr) {
    use std::io::BufRead;
    let mut child = std::process::Command::new("socat")
        .args(["-d", "-d", "TCP-LISTEN:0,bind=127.0.0.1", far])
        .stdin(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("socat");
    let mut lines = std::io::BufReader::new(child.stderr.take().unwrap()).lines();
    // "... listening on AF=2 127.0.0.1:PORT"; stderr closes if socat fails.
    let addr = lines
        .by_ref()
        .map_while(Result::ok)
        .find_map(|l| {
            l.split("listening on AF=2 ")
                .nth(1)
                .and_then(|a| a.trim().parse().ok())
        })
        .expect("socat's listening address");
    thread::spawn(move || lines.for_each(drop));
    (child, addr)
}

// ---------------------------------------------------------------------------------
// 2. Wire efficiency

/// Transactions per second the wire allows: half duplex (one outstanding: request
/// then reply) or full duplex (pipelined: the longer direction limits).
fn wire_limit(baud: u32, qty: u16, full_duplex: bool) -> f64 {
    let bytes = if full_duplex {
        REQ.max(reply_len(qty))
    } else {
        REQ + reply_len(qty)
    };
    f64::from(baud) / 10.0 / bytes as f64
}

/// Keeps `window` FC 03 reads outstanding (1 = polling) for `budget`, through
/// `send`/`recv` (which returns how many replies it read); returns transactions per
/// second between the last warm-up reply and the last reply before the deadline.
fn throughput(
    window: usize,
    qty: u16,
    budget: Duration,
    mut send: impl FnMut(&[u8]),
    mut recv: impl FnMut() -> usize,
) -> f64 {
    const WARM: usize = 8;
    let mut tid = 0u16;
    let mut request = || {
        tid = tid.wrapping_add(1);
        read_req(tid, 1, 0, qty)
    };
    for _ in 0..window {
        send(&request());
    }
    let mut done = 0usize;
    let (mut start, mut last, mut counted) = (Instant::now(), Instant::now(), 0usize);
    let deadline = Instant::now() + budget;
    let mut sent = window;
    loop {
        let n = recv();
        for _ in 0..n {
            done += 1;
            let now = Instant::now();
            if done == WARM {
                start = now;
            } else if done > WARM && now <= deadline {
                (last, counted) = (now, counted + 1);
            }
            if now < deadline && sent < MAX_TRANSACTIONS {
                send(&request());
                sent += 1;
            }
        }
        if done == sent {
            break;
        }
    }
    // Replies after the deadline (the pipeline draining) are not counted.
    counted as f64 / (last - start).as_secs_f64()
}

/// Polls (or pipelines) through the gateway.
fn tcp_throughput(s: &mut TcpStream, window: usize, qty: u16, budget: Duration) -> f64 {
    let mut rd = s.try_clone().unwrap();
    throughput(
        window,
        qty,
        budget,
        |req| s.write_all(req).expect("send"),
        || {
            let reply = read_frame(&mut rd);
            assert_eq!(
                reply.len(),
                reply_len(qty),
                "not a normal reply: {reply:02X?}"
            );
            1
        },
    )
}

/// Polls (or pipelines) straight to the simulator on the pty.
fn raw_throughput(m: &mut RawLine, window: usize, qty: u16, budget: Duration) -> f64 {
    let m = std::cell::RefCell::new(m);
    let mut bytes = 0usize;
    let len = reply_len(qty);
    throughput(
        window,
        qty,
        budget,
        |req| m.borrow_mut().send(req),
        || {
            let got = m.borrow_mut().recv(1, Duration::from_secs(5)).len();
            assert!(got > 0, "the simulator stopped answering");
            let before = bytes / len;
            bytes += got;
            bytes / len - before
        },
    )
}

fn wire(r: &mut Report) {
    const BUDGET: Duration = Duration::from_secs(3);
    let mut t = String::from(
        "| baud | max_in_flight (window) | registers | wire limit | direct to the simulator | through mbgate | mbgate / limit |\n|---|---|---|---|---|---|---|\n",
    );
    for baud in [9600u32, 19200, 115200] {
        for (pipelined, in_flight, window) in [(false, 1, 1), (true, 4, 8)] {
            eprintln!(
                "wire: {baud} baud, {}",
                if pipelined { "pipelined" } else { "polling" }
            );
            let b = baud.to_string();
            let mut sim_args = vec!["--baud", b.as_str()];
            if pipelined {
                sim_args.push("--pipeline");
            }
            let line = Line::start(&sim_args);
            let direct: Vec<f64> = {
                let mut m = line.raw();
                [1, 10]
                    .iter()
                    .map(|&q| raw_throughput(&mut m, window.min(in_flight), q, BUDGET))
                    .collect()
            };
            let inf = format!("max_in_flight = {in_flight}");
            let gw = line.gateway(&[&inf], &[]);
            let mut s = connect(&gw);
            for (i, qty) in [1u16, 10].into_iter().enumerate() {
                let got = tcp_throughput(&mut s, window, qty, BUDGET);
                let limit = wire_limit(baud, qty, pipelined);
                let eff = got / limit;
                let _ = writeln!(
                    t,
                    "| {baud} | {in_flight} ({window}) | {qty} | {limit:.1}/s | {:.1}/s ({}) | {got:.1}/s | **{}** |",
                    direct[i],
                    pct(direct[i] / limit),
                    pct(eff)
                );
                let (target, ok) = if pipelined {
                    ("≥ 95 % of full duplex", eff >= 0.95)
                } else {
                    ("≥ 97 % of half duplex", eff >= 0.97)
                };
                r.row(
                    "wire",
                    &format!(
                        "wire efficiency {baud} baud, max_in_flight {in_flight}, FC 03 × {qty}"
                    ),
                    format!("{} ({got:.1} of {limit:.1}/s)", pct(eff)),
                    target,
                    Some(ok),
                );
            }
        }
    }
    r.detail(
        "Wire efficiency (simulator paces 10 bits a byte each way; one master, 3 s a point after 8 warm-up transactions)",
        &command("wire"),
        &t,
    );
}

// ---------------------------------------------------------------------------------
// 3. Fairness

/// What one polling master saw inside the measuring window.
#[derive(Default)]
struct Seen {
    latencies: Vec<Duration>,
}

/// `n` masters poll FC 03 × 1 through the gateway at once. The window opens after
/// `warm` and closes at `warm + window`; a transaction counts if it was sent and
/// answered inside it.
fn poll_together(gw: &Gateway, n: usize, warm: Duration, window: Duration) -> Vec<Seen> {
    let barrier = Arc::new(Barrier::new(n + 1));
    let addr = gw.addr;
    let masters: Vec<_> = (0..n)
        .map(|_| {
            let barrier = barrier.clone();
            let mut s = TcpStream::connect(addr).expect("connect");
            s.set_nodelay(true).unwrap();
            s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
            thread::spawn(move || {
                barrier.wait();
                let t0 = Instant::now();
                let (open, close) = (t0 + warm, t0 + warm + window);
                let mut seen = Seen::default();
                let mut tid = 0u16;
                for _ in 0..MAX_TRANSACTIONS {
                    let sent = Instant::now();
                    if sent >= close {
                        break;
                    }
                    tid = tid.wrapping_add(1);
                    let took = tcp_read(&mut s, tid, 1);
                    if sent >= open && sent + took <= close {
                        seen.latencies.push(took);
                    }
                }
                seen
            })
        })
        .collect();
    barrier.wait();
    masters.into_iter().map(|m| m.join().unwrap()).collect()
}

/// Keeps 16 requests outstanding on its own connection until `stop`.
fn pipeliner(gw: &Gateway, stop: Instant) -> thread::JoinHandle<usize> {
    let mut s = connect(gw);
    thread::spawn(move || {
        let mut rd = s.try_clone().unwrap();
        let mut n = 0;
        throughput(
            16,
            1,
            stop.saturating_duration_since(Instant::now()),
            |req| s.write_all(req).expect("send"),
            || {
                read_frame(&mut rd);
                n += 1;
                1
            },
        );
        n
    })
}

fn fairness(r: &mut Report) {
    const BAUD: u32 = 115_200;
    eprintln!("fairness: 1, 10, 100 masters polling at {BAUD} baud");
    let line = Line::start(&["--baud", "115200"]);
    // Room for every master and every pipelined request: no 0x06, no refusals. Every
    // request its own transaction: the masters poll the same reads, which coalescing
    // would merge (measured on its own, `-- coalesce`).
    let gw = line.gateway(
        &["queue_depth = 256", "coalesce = false"],
        &["max_connections = 128"],
    );
    let wire_t = Duration::from_secs_f64(1.0 / wire_limit(BAUD, 1, false));
    let mut t = String::from(
        "| masters | window | throughput | of wire limit | share min / max of mean | p50 | p99 | p99 / (masters × T₁) |\n|---|---|---|---|---|---|---|---|\n",
    );
    let mut t1 = None;
    for n in [1usize, 10, 100] {
        // About 30 rounds of every master, at least 3 s.
        let window = (wire_t * (30 * n) as u32).max(Duration::from_secs(3));
        let seen = poll_together(&gw, n, Duration::from_millis(500), window);
        let counts: Vec<usize> = seen.iter().map(|s| s.latencies.len()).collect();
        let total: usize = counts.iter().sum();
        let mean = total as f64 / n as f64;
        let (lo, hi) = (
            *counts.iter().min().unwrap() as f64 / mean,
            *counts.iter().max().unwrap() as f64 / mean,
        );
        let all: Vec<Duration> = seen.into_iter().flat_map(|s| s.latencies).collect();
        let sp = spread(&all);
        // One transaction time: a single master's median, measured here first.
        let t1 = *t1.get_or_insert(sp.p50);
        let rate = total as f64 / window.as_secs_f64();
        let of_wire = rate / wire_limit(BAUD, 1, false);
        let bound = t1 * n as u32;
        let ratio = sp.p99.as_secs_f64() / bound.as_secs_f64();
        let _ = writeln!(
            t,
            "| {n} | {:.1} s | {rate:.1}/s | {} | {:.3} / {:.3} | {} | {} | {ratio:.3} |",
            window.as_secs_f64(),
            pct(of_wire),
            lo,
            hi,
            ms(sp.p50),
            ms(sp.p99),
        );
        r.row(
            "fairness",
            &format!("{n} masters: throughput"),
            format!(
                "{rate:.1}/s = {} of the wire limit, {} of one master's",
                pct(of_wire),
                pct(rate * t1.as_secs_f64())
            ),
            "at the wire limit",
            None,
        );
        if n > 1 {
            let worst = (1.0 - lo).max(hi - 1.0);
            r.row(
                "fairness",
                &format!("{n} masters: each master's share"),
                format!("within {} of the mean", pct(worst)),
                "within 10 %",
                Some(worst <= 0.10),
            );
        }
        r.row(
            "fairness",
            &format!("{n} masters: p99 latency"),
            format!("{} = {ratio:.3} × ({n} × T₁ = {})", ms(sp.p99), ms(bound)),
            "≤ 1.2 × masters × T₁",
            Some(ratio <= 1.2),
        );
    }
    let t1 = t1.expect("measured");

    // A pipelining master beside a polling one.
    eprintln!("fairness: a poller alone, then beside a master pipelining 16");
    let budget = Duration::from_secs(4);
    let alone = spread(&poll_together(&gw, 1, Duration::from_millis(300), budget)[0].latencies);
    let stop = Instant::now() + budget + Duration::from_millis(600);
    let p = pipeliner(&gw, stop);
    let beside = poll_together(&gw, 1, Duration::from_millis(300), budget);
    let piped = p.join().unwrap();
    let beside = spread(&beside[0].latencies);
    let extra = beside.p99.saturating_sub(alone.p99);
    let _ = writeln!(
        t,
        "\nPoller alone: p50 {}, p99 {}; beside a master pipelining 16 ({piped} replies to it): p50 {}, p99 {} (+{} = {:.2} T₁). T₁ = {} (wire time {}).",
        ms(alone.p50),
        ms(alone.p99),
        ms(beside.p50),
        ms(beside.p99),
        ms(extra),
        extra.as_secs_f64() / t1.as_secs_f64(),
        ms(t1),
        ms(wire_t),
    );
    r.row(
        "fairness",
        "poller's p99 beside a master pipelining 16",
        format!(
            "{} vs {} alone (+{:.2} T₁)",
            ms(beside.p99),
            ms(alone.p99),
            extra.as_secs_f64() / t1.as_secs_f64()
        ),
        "≤ alone + 2 T₁",
        Some(extra <= t1 * 2),
    );
    peak_rss_row(
        r,
        "fairness",
        "peak RSS of mbgate after these runs (100 masters polling at most)",
        proc_status(gw.proc.pid(), "VmHWM"),
    );
    r.detail(
        &format!("Fairness ({BAUD} baud, max_in_flight 1, queue_depth 256, max_connections 128; FC 03 × 1; T₁ = one master's median transaction time = {}, wire time {})", ms(t1), ms(wire_t)),
        &command("fairness"),
        &t,
    );
}

// ---------------------------------------------------------------------------------
// 4. Footprint

/// A `kB` field of /proc/PID/status.
fn proc_status(pid: u32, key: &str) -> u64 {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("status");
    s.lines()
        .find_map(|l| l.strip_prefix(&format!("{key}:")))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no {key} in /proc/{pid}/status"))
}

/// The peak-RSS target: at most 8 MiB (`kb` from VmHWM).
fn peak_rss_row(r: &mut Report, scenario: &'static str, measure: &str, kb: u64) {
    r.row(
        scenario,
        measure,
        format!("{:.2} MiB", kb as f64 / 1024.0),
        "≤ 8 MiB",
        Some(kb <= 8 * 1024),
    );
}

/// utime + stime of a process, in clock ticks (/proc/PID/stat fields 14 and 15).
fn cpu_ticks(pid: u32) -> u64 {
    let s = std::fs::read_to_string(format!("/proc/{pid}/stat")).expect("stat");
    // The command name may hold spaces; the fields after it are plain.
    let rest = &s[s.rfind(')').expect("comm") + 2..];
    let f: Vec<u64> = rest
        .split_whitespace()
        .map(|x| x.parse().unwrap_or(0))
        .collect();
    // rest starts at field 3 (state): field k is f[k - 3].
    f[14 - 3] + f[15 - 3]
}

fn clock_ticks_per_second() -> u64 {
    // SAFETY: sysconf has no preconditions.
    (unsafe { libc::sysconf(libc::_SC_CLK_TCK) }).max(1) as u64
}

fn file_size(path: &Path) -> u64 {
    std::fs::metadata(path).map(|m| m.len()).unwrap_or(0)
}

fn footprint(r: &mut Report) {
    eprintln!("footprint: start-up, idle CPU with 10 masters, RSS with 100");
    let line = Line::start(&[]);
    let mut t = String::from("| what | figure |\n|---|---|\n");

    // Time from spawn to the `listening on` line, five starts.
    let mut starts = Vec::new();
    for _ in 0..5 {
        let mut gw = line.gateway(&[], &[]);
        starts.push(gw.proc.ready_after());
        gw.terminate(Duration::from_secs(5));
    }
    let st = spread(&starts);
    let _ = writeln!(
        t,
        "| start to `listening on`, 5 starts | median {}, max {} |",
        ms(st.p50),
        ms(st.max)
    );
    r.row(
        "footprint",
        "start to listening (median of 5)",
        ms(st.p50),
        "(reported)",
        None,
    );

    let gw = line.gateway(&["queue_depth = 256"], &["max_connections = 128"]);
    let pid = gw.proc.pid();
    let rss_start = proc_status(pid, "VmRSS");
    let mut masters: Vec<TcpStream> = (0..10).map(|_| connect(&gw)).collect();
    for (i, m) in masters.iter_mut().enumerate() {
        tcp_read(m, i as u16, 1);
    }
    // Idle: 10 masters connected, nothing asked, for 10 s.
    let (ticks0, ns0, sw0) = (
        cpu_ticks(pid),
        cpu_ns(pid),
        proc_status(pid, "voluntary_ctxt_switches"),
    );
    thread::sleep(Duration::from_secs(10));
    let (ticks1, ns1, sw1) = (
        cpu_ticks(pid),
        cpu_ns(pid),
        proc_status(pid, "voluntary_ctxt_switches"),
    );
    let hz = clock_ticks_per_second();
    let idle_ms = (ticks1 - ticks0) as f64 * 1000.0 / hz as f64;
    let idle_exact = Duration::from_nanos(ns1 - ns0);
    let _ = writeln!(
        t,
        "| CPU while idle, 10 masters connected, 10 s | utime+stime {} ticks ({idle_ms:.0} ms at {hz} ticks/s); schedstat {}; {} voluntary context switches |",
        ticks1 - ticks0,
        ms(idle_exact),
        sw1 - sw0
    );
    r.row(
        "footprint",
        "CPU while idle, 10 masters connected, 10 s",
        format!(
            "{} (schedstat), {} ticks, {} wake-ups",
            ms(idle_exact),
            ticks1 - ticks0,
            sw1 - sw0
        ),
        "< 10 ms",
        Some(idle_exact < Duration::from_millis(10) && idle_ms < 10.0),
    );

    // 100 masters connected, each has had a reply.
    masters.extend((10..100).map(|_| connect(&gw)));
    let barrier = Arc::new(Barrier::new(masters.len()));
    let masters: Vec<TcpStream> = masters
        .into_iter()
        .enumerate()
        .map(|(i, mut m)| {
            let b = barrier.clone();
            thread::spawn(move || {
                b.wait();
                tcp_read(&mut m, i as u16, 10);
                m
            })
        })
        .collect::<Vec<_>>()
        .into_iter()
        .map(|h| h.join().unwrap())
        .collect();
    let (rss, hwm, threads) = (
        proc_status(pid, "VmRSS"),
        proc_status(pid, "VmHWM"),
        proc_status(pid, "Threads"),
    );
    let _ = writeln!(
        t,
        "| RSS: at start / with 100 masters connected / peak (VmHWM) | {rss_start} kB / {rss} kB / {hwm} kB ({threads} threads) |"
    );
    peak_rss_row(
        r,
        "footprint",
        "peak RSS with 100 connected masters (VmHWM)",
        hwm,
    );
    drop(masters);

    let bin = Path::new(env!("CARGO_BIN_EXE_mbgate"));
    let size = file_size(bin);
    let stripped = std::env::temp_dir().join(format!("mbgate-stripped-{}", std::process::id()));
    let stripped_size = std::process::Command::new("strip")
        .arg("-o")
        .arg(&stripped)
        .arg(bin)
        .status()
        .ok()
        .filter(|s| s.success())
        .map(|_| file_size(&stripped));
    let _ = std::fs::remove_file(&stripped);
    let stripped_text = stripped_size.map_or("strip not found".into(), |s| {
        format!("{:.2} MiB stripped", s as f64 / 1048576.0)
    });
    let _ = writeln!(
        t,
        "| release binary `target/release/mbgate` | {size} bytes ({:.2} MiB); {stripped_text} |",
        size as f64 / 1048576.0
    );
    r.row(
        "footprint",
        "release binary size",
        format!("{:.2} MiB ({stripped_text})", size as f64 / 1048576.0),
        "(reported)",
        None,
    );
    r.detail("Footprint (the mbgate process: /proc/PID/status, /proc/PID/stat, /proc/PID/task/*/schedstat)", &command("footprint"), &t);
}

// ---------------------------------------------------------------------------------
// 5. RTU

/// RTU bytes of an FC 03 read: address, function, address, quantity, CRC.
const RTU_REQ: usize = 8;

/// RTU bytes of the reply to an FC 03 read of `qty` registers: address, function, byte
/// count, 2 × qty, CRC.
fn rtu_reply_len(qty: u16) -> usize {
    5 + 2 * usize::from(qty)
}

/// The simulator as an RTU device paced at `baud`, answering once probed, and the
/// gateway in front of it at the same speed without flow control.
fn rtu_line(baud: u32) -> (Line, Gateway) {
    let probe = mbgate::frame::rtu::encode(1, &[0x03, 0, 0, 0, 1]);
    let speed = baud.to_string();
    let line = Line::start_probed(
        &["--framing", "rtu", "--baud", &speed],
        &probe,
        rtu_reply_len(1),
    );
    let cfg = Cfg::new(&line.socat.gw)
        .serial("framing = \"rtu\"")
        .serial("flow_control = \"none\"")
        .serial(&format!("baud_rate = {baud}"));
    let gw = line.gateway_with(cfg, &[], &[]);
    (line, gw)
}

/// One master polls FC 03 through `mbgate run --framing rtu` at 9600 baud against the
/// simulator (`--framing rtu --baud 9600`): transactions per second against the wire
/// limit, and the gateway's CPU time meanwhile (utime + stime from /proc/PID/stat, and
/// schedstat), which a busy-waiting gateway would drive towards a whole core.
fn rtu(r: &mut Report) {
    const BAUD: u32 = 9600;
    const CPU_BUDGET: Duration = Duration::from_secs(10);
    const BUDGET: Duration = Duration::from_secs(3);
    let (_line, gw) = rtu_line(BAUD);
    let pid = gw.proc.pid();
    let mut s = connect(&gw);
    let char_time = 10.0 / f64::from(BAUD);
    // 3.5 character times, the gap mbgate leaves before each request.
    let t35 = 3.5 * char_time;
    let mut t = String::from(
        "| registers | wire limit (no gaps) | limit with the 3.5-character gap before each request | through mbgate | mbgate / limit (no gaps) | mbgate / limit (with gap) |\n|---|---|---|---|---|---|\n",
    );
    let mut cpu_row = String::new();
    for qty in [1u16, 10] {
        let bytes = (RTU_REQ + rtu_reply_len(qty)) as f64;
        let limit = 1.0 / (bytes * char_time);
        let limit_gap = 1.0 / (bytes * char_time + t35);
        let budget = if qty == 1 { CPU_BUDGET } else { BUDGET };
        eprintln!("rtu: {BAUD} baud, FC 03 × {qty}, {budget:?}");
        let (ticks0, ns0) = (cpu_ticks(pid), cpu_ns(pid));
        let got = tcp_throughput(&mut s, 1, qty, budget);
        let (ticks1, ns1) = (cpu_ticks(pid), cpu_ns(pid));
        let _ = writeln!(
            t,
            "| {qty} | {limit:.1}/s | {limit_gap:.1}/s | {got:.1}/s | {} | **{}** |",
            pct(got / limit),
            pct(got / limit_gap)
        );
        r.row(
            "rtu",
            &format!("RTU throughput {BAUD} baud, one master polling FC 03 × {qty}"),
            format!(
                "{got:.1}/s = {} of the wire limit with the 3.5-character gap ({limit_gap:.1}/s), {} without ({limit:.1}/s)",
                pct(got / limit_gap),
                pct(got / limit)
            ),
            "(reported)",
            None,
        );
        if qty == 1 {
            let hz = clock_ticks_per_second();
            let busy = (ticks1 - ticks0) as f64 / hz as f64;
            let share = busy / budget.as_secs_f64();
            let exact = (ns1 - ns0) as f64 / 1e9 / budget.as_secs_f64();
            cpu_row = format!(
                "utime+stime {} ticks in {} s = {} of a core (schedstat {})",
                ticks1 - ticks0,
                budget.as_secs(),
                pct(share),
                pct(exact)
            );
            r.row(
                "rtu",
                &format!("mbgate CPU, one master polling as fast as it can, RTU {BAUD} baud"),
                format!("{} of a core (schedstat {})", pct(share), pct(exact)),
                "< 5 % of a core",
                Some(share < 0.05),
            );
        }
    }
    let _ = writeln!(t, "\nCPU while polling FC 03 × 1 for 10 s: {cpu_row}.");
    r.detail(
        "RTU (the simulator with --framing rtu --baud 9600 paces 10 bits a byte each way; the wire limit counts request and reply bytes at 10 bits a byte, and the second limit adds the 3.5 character times mbgate waits before each request)",
        &command("rtu"),
        &t,
    );
}

/// A master polls a dead unit (2) in a tight loop beside a master polling a healthy
/// one (1), RTU at 19 200 baud, every `[relay]` key at its default: once the dead unit
/// is backed off, how fast its 0x0B answers come against the line's pace, what they
/// cost the gateway (utime + stime and schedstat, the healthy master idle), and the
/// healthy unit's throughput beside it against alone (probes of the dead unit
/// included).
fn rtu_backoff(r: &mut Report) {
    use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
    const BAUD: u32 = 19_200;
    const ALONE: Duration = Duration::from_secs(5);
    const CPU_WINDOW: Duration = Duration::from_secs(5);
    const BESIDE: Duration = Duration::from_secs(10);
    let (_line, gw) = rtu_line(BAUD);
    let pid = gw.proc.pid();
    let mut healthy = connect(&gw);
    eprintln!("rtu-backoff: the healthy unit alone, {ALONE:?}");
    let alone = tcp_throughput(&mut healthy, 1, 1, ALONE);

    let answered = Arc::new(AtomicUsize::new(0));
    let stop = Arc::new(AtomicBool::new(false));
    let (answered2, stop2) = (answered.clone(), stop.clone());
    let mut s = connect(&gw);
    let dead = thread::spawn(move || {
        let mut tid = 0u16;
        let mut slow = 0usize;
        while !stop2.load(Ordering::Relaxed) && tid < u16::MAX {
            tid += 1;
            let t = Instant::now();
            s.write_all(&read_req(tid, 2, 0, 1)).expect("send");
            let reply = read_frame(&mut s);
            assert_eq!(reply[7..], [0x83, 0x0B], "not 0x0B: {reply:02X?}");
            if t.elapsed() > Duration::from_millis(200) {
                slow += 1;
            }
            answered2.fetch_add(1, Ordering::Relaxed);
        }
        slow
    });
    // Three timeouts of 1 s and their 100 ms guards back it off.
    eprintln!("rtu-backoff: backing the dead unit off");
    thread::sleep(Duration::from_millis(3500));
    eprintln!("rtu-backoff: the dead unit polled alone, {CPU_WINDOW:?}");
    let (n0, ticks0, ns0, t0) = (
        answered.load(Ordering::Relaxed),
        cpu_ticks(pid),
        cpu_ns(pid),
        Instant::now(),
    );
    thread::sleep(CPU_WINDOW);
    let (n1, ticks1, ns1, t1) = (
        answered.load(Ordering::Relaxed),
        cpu_ticks(pid),
        cpu_ns(pid),
        Instant::now(),
    );
    eprintln!("rtu-backoff: the healthy unit beside it, {BESIDE:?}");
    let beside = tcp_throughput(&mut healthy, 1, 1, BESIDE);
    stop.store(true, Ordering::Relaxed);
    let slow = dead.join().unwrap();

    let secs = (t1 - t0).as_secs_f64();
    let rate = (n1 - n0) as f64 / secs;
    // The line's shortest transaction: 8 bytes out, 5 back, each after 3.5 characters.
    let char_time = 10.0 / f64::from(BAUD);
    let line_rate = 1.0 / (13.0 * char_time + 2.0 * 0.00175);
    let share = (ticks1 - ticks0) as f64 / clock_ticks_per_second() as f64 / secs;
    let exact = (ns1 - ns0) as f64 / 1e9 / secs;
    r.row(
        "rtu-backoff",
        "backed-off unit polled in a tight loop, RTU 19 200 baud: 0x0B answers and mbgate CPU",
        format!(
            "{rate:.1}/s (the line's pace {line_rate:.1}/s); {} of a core (schedstat {})",
            pct(share),
            pct(exact)
        ),
        "≤ the line's pace; < 5 % of a core",
        Some(rate <= line_rate * 1.05 && share < 0.05),
    );
    r.row(
        "rtu-backoff",
        "healthy unit beside it: throughput against alone",
        format!(
            "{beside:.1}/s beside, {alone:.1}/s alone = {} (dead unit: {slow} answers slower than 200 ms, the 3 timeouts that backed it off and its probes)",
            pct(beside / alone)
        ),
        "≥ 90 %",
        Some(beside >= alone * 0.9),
    );
}

// ---------------------------------------------------------------------------------
// 7. Many masters, one read (docs/masters.md, "Many masters, one read")

/// FC 03 × 10 at `addr` through the gateway, the reply checked against the
/// simulator's values (`--fill address`: each register holds its address), except
/// register 0 when `at_least` is given: the writer's, which must be no older than the
/// last write answered before the read was sent.
fn block_read(s: &mut TcpStream, tid: u16, addr: u16, at_least: Option<u16>) {
    s.write_all(&read_req(tid, 1, addr, 10)).expect("send");
    let reply = read_frame(s);
    let mut want: Vec<u16> = (addr..addr + 10).collect();
    if let Some(least) = at_least {
        assert_eq!(
            reply.len(),
            reply_len(10),
            "not a normal reply: {reply:02X?}"
        );
        let got = u16::from_be_bytes([reply[9], reply[10]]);
        assert!(
            got >= least,
            "a value older than the request: {got} after write {least} was answered"
        );
        want[0] = got;
    }
    assert_eq!(
        reply,
        read_reply(tid, 1, &want),
        "not the device's values at {addr}"
    );
}

/// `n` masters each poll FC 03 × 10 at `addr(i)` as fast as they are answered, for
/// `warm + window`. Returns the replies each got inside the window (answered after it
/// opened and before it closed: a master that waits seconds for its turn still counts
/// at its rate), the replies they got in all, and the gateway's CPU time over the
/// window.
fn poll_blocks(
    gw: &Gateway,
    n: usize,
    addr: impl Fn(usize) -> u16,
    (warm, window): (Duration, Duration),
    acked: Option<&Arc<AtomicU16>>,
) -> (Vec<Polled>, usize, u64) {
    let barrier = Arc::new(Barrier::new(n + 1));
    let masters: Vec<_> = (0..n)
        .map(|i| {
            let (barrier, a, acked) = (barrier.clone(), addr(i), acked.cloned());
            let mut s = gw.connect();
            // Without coalescing a master waits for all the others at 9600 baud.
            s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
            thread::spawn(move || {
                barrier.wait();
                let t0 = Instant::now();
                let (open, close) = (t0 + warm, t0 + warm + window);
                let (mut count, mut all, mut tid) = (0, 0, 0u16);
                let (mut first, mut last) = (None, close);
                for _ in 0..MAX_TRANSACTIONS {
                    if Instant::now() >= close {
                        break;
                    }
                    tid = tid.wrapping_add(1);
                    let least = acked.as_ref().map(|a| a.load(Ordering::SeqCst));
                    block_read(&mut s, tid, a, least);
                    all += 1;
                    let now = Instant::now();
                    if (open..=close).contains(&now) {
                        count += 1;
                        first.get_or_insert(now);
                        last = now;
                    }
                }
                // Replies per second between its first and last in the window: not
                // quantised by where the window's edges fall.
                let rate = first
                    .filter(|_| count >= 3)
                    .map(|f| (count - 1) as f64 / (last - f).as_secs_f64());
                (Polled { count, rate }, all)
            })
        })
        .collect();
    barrier.wait();
    let pid = gw.proc.pid();
    thread::sleep(warm);
    let cpu0 = cpu_ns(pid);
    thread::sleep(window);
    let cpu = cpu_ns(pid) - cpu0;
    let got: Vec<(Polled, usize)> = masters.into_iter().map(|m| m.join().unwrap()).collect();
    let all = got.iter().map(|g| g.1).sum();
    (got.into_iter().map(|g| g.0).collect(), all, cpu)
}

/// What one polling master got inside the window.
struct Polled {
    count: usize,
    /// Its rate from its first to its last reply in the window, if it had 3 or more.
    rate: Option<f64>,
}

/// The slowest master's rate and the mean, a second: from each one's own replies when
/// every master had several in the window, else from the counts.
fn rates(polled: &[Polled], window: Duration) -> (f64, f64) {
    let n = polled.len() as f64;
    if let Some(rates) = polled.iter().map(|p| p.rate).collect::<Option<Vec<f64>>>() {
        let min = rates.iter().copied().fold(f64::INFINITY, f64::min);
        return (min, rates.iter().sum::<f64>() / n);
    }
    let secs = window.as_secs_f64();
    let counts = polled.iter().map(|p| p.count);
    let min = counts.clone().min().unwrap_or(0) as f64 / secs;
    (min, counts.sum::<usize>() as f64 / n / secs)
}

/// The last value of counter `name` the gateway logged (it logs them all on exit).
fn logged(gw: &Gateway, name: &str) -> u64 {
    let log = gw.log();
    let at = log
        .rfind(&format!(" {name}="))
        .unwrap_or_else(|| panic!("no {name} in the log"));
    log[at + name.len() + 2..]
        .split(|c: char| !c.is_ascii_digit())
        .next()
        .and_then(|n| n.parse().ok())
        .expect("a number")
}

fn coalesce(r: &mut Report) {
    const MASTERS: usize = 100;
    let mut t = String::from(
        "| scenario | gateway | replies in the window | per master: min / mean | transactions on the line | mbgate CPU per reply |\n|---|---|---|---|---|---|\n",
    );

    // The same read, 9600 baud.
    let sim = ["--baud", "9600", "--registers", "200", "--fill", "address"];
    let line = Line::start(&sim);
    let times = (Duration::from_secs(1), Duration::from_secs(4));
    let mut alone = 0.0;
    let mut each = [0.0; 2];
    for (i, on) in [true, false].into_iter().enumerate() {
        let setting = format!("coalesce = {on}");
        let relay = ["queue_depth = 256", setting.as_str()];
        if on {
            eprintln!("coalesce: one master alone, FC 03 x 10 at 9600 baud");
            let mut gw = line.gateway(&relay, &[]);
            let (c, all, _) = poll_blocks(&gw, 1, |_| 0, times, None);
            alone = rates(&c, times.1).0;
            gw.terminate(Duration::from_secs(10));
            let on_line = logged(&gw, "serial_bytes_out") / REQ as u64;
            let _ = writeln!(
                t,
                "| 1 master, FC 03 × 10 at 0, 9600 baud | coalesce on | {} | {alone:.2}/s | {on_line} for {all} replies in all | |",
                c[0].count
            );
        }
        // A gateway of its own: its counters are this run's.
        let mut gw = line.gateway(&relay, &["max_connections = 128"]);
        eprintln!("coalesce: {MASTERS} masters polling the same read, coalesce = {on}");
        let (c, all, cpu) = poll_blocks(&gw, MASTERS, |_| 0, times, None);
        let (min, mean) = rates(&c, times.1);
        // Off, most masters get one reply or none in the window: their mean says it.
        each[i] = if on { min } else { mean };
        let total: usize = c.iter().map(|p| p.count).sum();
        gw.terminate(Duration::from_secs(10));
        // The simulator was probed straight on the pty, not through mbgate.
        let on_line = logged(&gw, "serial_bytes_out") / REQ as u64;
        let _ = writeln!(
            t,
            "| {MASTERS} masters, the same FC 03 × 10, 9600 baud | coalesce {} | {total} | {min:.2}/s / {mean:.2}/s | {on_line} for {all} replies in all ({} coalesced) | {} |",
            if on { "on" } else { "off" },
            logged(&gw, "coalesced"),
            us(Duration::from_nanos(cpu / total.max(1) as u64)),
        );
    }
    r.row(
        "coalesce",
        &format!("{MASTERS} masters polling the same FC 03 × 10, 9600 baud: each master's poll rate"),
        format!(
            "{:.2}/s (slowest master) = {} of one master alone ({alone:.2}/s); coalescing off: {:.3}/s (mean)",
            each[0],
            pct(each[0] / alone),
            each[1]
        ),
        "≥ 50 % of one master alone",
        Some(each[0] >= alone * 0.5),
    );

    // Different registers: nothing to merge. 115200 baud, so the window holds
    // thousands of transactions and the CPU per reply means something.
    let sim = [
        "--baud",
        "115200",
        "--registers",
        "200",
        "--fill",
        "address",
    ];
    let line = Line::start(&sim);
    let baseline = std::env::var_os("MBGATE_BENCH_BASELINE");
    let mut runs: Vec<(String, Option<&std::ffi::OsStr>, &str)> = vec![
        ("this build, coalesce on".into(), None, "coalesce = true"),
        ("this build, coalesce off".into(), None, "coalesce = false"),
    ];
    if let Some(b) = baseline.as_deref() {
        runs.push((
            format!("baseline `{}`", Path::new(b).display()),
            Some(b),
            "",
        ));
    }
    // The builds take turns, ROUNDS times and in a rotating order, so a change in the
    // machine's load falls on all of them alike.
    const ROUNDS: usize = 4;
    let short = (Duration::from_millis(500), Duration::from_secs(2));
    let mut sums = vec![(0usize, 0u64, 0usize, Vec::new()); runs.len()];
    for round in 0..ROUNDS {
        // Each round in another order: none is always first after the 9600 baud runs.
        for i in (0..runs.len()).map(|k| (k + round) % runs.len()) {
            let (name, program, setting) = &runs[i];
            eprintln!("coalesce: {MASTERS} masters on {MASTERS} registers, {name}, round {round}");
            let mut cfg = Cfg::new(&line.socat.gw)
                .serial("silence_floor_ms = 0")
                .log_level("info")
                .relay("queue_depth = 256")
                .tcp("max_connections = 128");
            if !setting.is_empty() {
                cfg = cfg.relay(setting);
            }
            let launch = match program {
                Some(p) => Launch::default().program(p),
                None => Launch::default(),
            };
            let mut gw = Gateway::launch(&cfg, line.dir.path(), launch);
            let (c, _, cpu) = poll_blocks(&gw, MASTERS, |i| i as u16, short, None);
            gw.terminate(Duration::from_secs(10));
            let n: usize = c.iter().map(|p| p.count).sum();
            let sum = &mut sums[i];
            sum.0 += n;
            sum.1 += cpu;
            if program.is_none() {
                sum.2 += logged(&gw, "coalesced") as usize;
            }
            sum.3.push(Duration::from_nanos(cpu / n.max(1) as u64));
        }
    }
    let mut cpus = Vec::new();
    for ((name, program, _), (total, cpu, coalesced, each)) in runs.iter().zip(sums) {
        let per_reply = Duration::from_nanos(cpu / total.max(1) as u64);
        let rate = total as f64 / (short.1.as_secs_f64() * ROUNDS as f64);
        let coalesced = if program.is_none() {
            format!("{coalesced} coalesced")
        } else {
            "-".into()
        };
        let rounds: Vec<String> = each.iter().map(|d| us(*d)).collect();
        let _ = writeln!(
            t,
            "| {MASTERS} masters, {MASTERS} different FC 03 × 10, 115200 baud ({ROUNDS} rounds of {} s) | {name} | {total} | {:.2}/s each | {coalesced} | {} (rounds: {}) |",
            short.1.as_secs(),
            rate / MASTERS as f64,
            us(per_reply),
            rounds.join(", ")
        );
        cpus.push((name.clone(), per_reply));
    }
    r.row(
        "coalesce",
        &format!(
            "{MASTERS} masters on {MASTERS} different registers, 115200 baud: mbgate CPU per reply"
        ),
        cpus.iter()
            .map(|(n, c)| format!("{n}: {}", us(*c)))
            .collect::<Vec<_>>()
            .join("; "),
        "no worse than without coalescing (within noise)",
        None,
    );

    // Mixed: 10 masters read the block a writer writes every 100 ms, 9600 baud.
    let line = Line::start(&["--baud", "9600", "--registers", "200", "--fill", "address"]);
    let mut gw = line.gateway(&[], &[]);
    eprintln!("coalesce: 10 masters reading, one writing every 100 ms, 9600 baud");
    let acked = Arc::new(AtomicU16::new(0));
    let mixed = (Duration::from_millis(500), Duration::from_secs(4));
    let stop = Instant::now() + mixed.0 + mixed.1;
    let writer = {
        let acked = acked.clone();
        let mut s = gw.connect();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        thread::spawn(move || {
            let mut n = 0u16;
            while Instant::now() < stop {
                n += 1;
                let reply = common::transact(&mut s, &write_req(n, 1, 0, &[n]));
                assert_eq!(reply[7], 0x10, "the write failed: {reply:02X?}");
                acked.store(n, Ordering::SeqCst);
                thread::sleep(Duration::from_millis(100));
            }
            n
        })
    };
    let (c, _, _) = poll_blocks(&gw, 10, |_| 0, mixed, Some(&acked));
    let writes = writer.join().unwrap();
    let total: usize = c.iter().map(|p| p.count).sum();
    gw.terminate(Duration::from_secs(10));
    let coalesced = logged(&gw, "coalesced");
    let _ = writeln!(
        t,
        "| 10 masters reading FC 03 × 10 at 0, one writing register 0 every 100 ms, 9600 baud | coalesce on | {total} | {:.2}/s / {:.2}/s | ({coalesced} coalesced; {writes} writes) | |",
        rates(&c, mixed.1).0,
        rates(&c, mixed.1).1,
    );
    r.row(
        "coalesce",
        "10 masters reading a block while one writes to it every 100 ms: replies older than their request",
        format!("0 of {total} (every reply checked; {writes} writes, {coalesced} reads coalesced)"),
        "none",
        Some(true),
    );
    r.detail(
        "Many masters, one read (the simulator with --fill address paces 10 bits a byte each way; 1 s warm-up, then a 4 s window; every reply checked against the device's values; transactions on the line counted from the bytes mbgate wrote)",
        &command("coalesce"),
        &t,
    );
}

// ---------------------------------------------------------------------------------
// 8. A device on the network, and RTU-over-TCP masters

/// A connection to `addr` whose first FC 03 read is answered: the simulator serves
/// one connection at a time, so this waits for the last one to be gone.
fn served(addr: &str) -> TcpStream {
    let start = Instant::now();
    loop {
        if let Ok(mut s) = TcpStream::connect(addr) {
            s.set_nodelay(true).unwrap();
            s.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
            if s.write_all(&read_req(1, 1, 0, 1)).is_ok() {
                let mut head = [0u8; 1];
                if std::io::Read::read(&mut s, &mut head).unwrap_or(0) == 1 {
                    let mut rest = vec![0u8; reply_len(1) - 1];
                    std::io::Read::read_exact(&mut s, &mut rest).unwrap();
                    return s;
                }
            }
        }
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "{addr} never served"
        );
        thread::sleep(Duration::from_millis(50));
    }
}

/// FC 03 to `mbgate sim --listen` (a Modbus/TCP device on the network) directly,
/// through a bare TCP byte pipe (socat), and through mbgate's TCP line: what the
/// gateway adds when the device is on the network.
fn tcp_line(r: &mut Report) {
    eprintln!("tcp-line: FC 03 straight to a device on TCP, through socat, through mbgate");
    const WARM: usize = 200;
    const N: usize = 2000;
    const ROUNDS: usize = 4;
    let dir = tempdir();
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let at = format!("127.0.0.1:{port}");
    let sim = [
        "sim",
        "--listen",
        &at,
        "--profile",
        "generic",
        "--log-level",
        "warn",
        "--headless",
    ];
    let _sim = Proc::start(&sim, "");
    let text = format!(
        "[[line]]\n[line.tcp]\naddress = \"{at}\"\n\n[[listen]]\naddress = \"127.0.0.1:0\"\n\n\
         [log]\nlevel = \"info\"\n"
    );
    let (mut direct, mut piped, mut through) = (vec![], vec![], vec![]);
    for _ in 0..ROUNDS {
        let mut s = served(&at);
        direct.extend(samples(WARM, N / ROUNDS, |tid| tcp_read(&mut s, tid, 1)));
        drop(s);
        let (mut pipe, addr) = socat_to(&format!("TCP:{at}"));
        let mut s = served(&addr.to_string());
        piped.extend(samples(WARM, N / ROUNDS, |tid| tcp_read(&mut s, tid, 1)));
        drop(s);
        let _ = pipe.kill();
        let _ = pipe.wait();
        let mut gw = Gateway::launch_text(&text, dir.path(), Launch::default());
        let mut s = served(&gw.addr.to_string());
        through.extend(samples(WARM, N / ROUNDS, |tid| tcp_read(&mut s, tid, 1)));
        drop(s);
        gw.terminate(Duration::from_secs(5));
    }
    let (d, p, g) = (spread(&direct), spread(&piped), spread(&through));
    let mut t = String::from("| path | p50 | p99 | max |\n|---|---|---|---|\n");
    for (path, x) in [
        ("TCP → sim (direct)", d),
        ("TCP → socat (a bare byte pipe) → TCP → sim", p),
        ("TCP → mbgate (a TCP line) → TCP → sim", g),
    ] {
        let _ = writeln!(
            t,
            "| {path} | {} | {} | {} |",
            us(x.p50),
            us(x.p99),
            us(x.max)
        );
    }
    let pipe50 = diff_us(d.p50, p.p50);
    for (q, added, pipe, before, after) in [
        ("p50", diff_us(d.p50, g.p50), pipe50, d.p50, g.p50),
        (
            "p99",
            diff_us(d.p99, g.p99),
            diff_us(d.p99, p.p99),
            d.p99,
            g.p99,
        ),
    ] {
        let _ = writeln!(
            t,
            "| added {q}: byte pipe {pipe:.0} µs, **mbgate {added:.0} µs** | | | |"
        );
        r.row(
            "tcp-line",
            &format!("TCP line: added latency {q}, FC 03 × 1"),
            format!(
                "{added:.0} µs ({} → {}); a byte pipe adds {pipe:.0} µs",
                us(before),
                us(after)
            ),
            "no more than the byte pipe + 50 µs",
            Some(added <= pipe + 50.0),
        );
    }
    r.detail(
        &format!("A device on the network ({N} samples a path, in {ROUNDS} rounds, each after {WARM} warm-up; `mbgate sim --listen`, unpaced)"),
        &command("tcp-line"),
        &t,
    );
}

/// FC 03 from an RTU-over-TCP master and from a Modbus/TCP master, taking turns,
/// through one gateway with both listeners to the simulator (RTU) on a pty: what the
/// RTU framing on the masters' side costs.
fn rtu_listener(r: &mut Report) {
    eprintln!("rtu-listener: FC 03 through an rtu listener and an mbap one");
    const WARM: usize = 200;
    const N: usize = 2000;
    const ROUNDS: usize = 4;
    // An RTU line at the fastest speed there is, to an unpaced simulator: a reply is
    // taken the moment its last byte arrives, so the line adds the least it can.
    let probe = mbgate::frame::rtu::encode(1, &[0x03, 0, 0, 0, 1]);
    let line = Line::start_probed(&["--framing", "rtu"], &probe, rtu_reply_len(1));
    let text = format!(
        "[[line]]\n[line.serial]\npath = {:?}\nframing = \"rtu\"\nflow_control = \"none\"\n\
         baud_rate = 4000000\nsilence_floor_ms = 0\n\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\n\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\nframing = \"rtu\"\n\n[log]\nlevel = \"info\"\n",
        line.socat.gw.display().to_string()
    );
    let mut gw = Gateway::launch_text(&text, line.dir.path(), Launch::default());
    let rtu_at = {
        let start = Instant::now();
        loop {
            let log = gw.proc.log();
            if let Some(a) = log.split("listening on ").nth(2) {
                break a.split_whitespace().next().unwrap().to_string();
            }
            assert!(start.elapsed() < Duration::from_secs(10), "no rtu listener");
            thread::sleep(Duration::from_millis(10));
        }
    };
    let mut m = connect(&gw);
    let mut rtu = TcpStream::connect(&rtu_at).unwrap();
    rtu.set_nodelay(true).unwrap();
    rtu.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let request = mbgate::frame::rtu::encode(1, &[0x03, 0, 0, 0, 1]);
    let mut rtu_read = |_tid: u16| {
        let t = Instant::now();
        rtu.write_all(&request).unwrap();
        let mut reply = vec![0u8; rtu_reply_len(1)];
        std::io::Read::read_exact(&mut rtu, &mut reply).unwrap();
        let took = t.elapsed();
        assert_eq!(reply[1], 0x03, "not a normal reply: {reply:02X?}");
        took
    };
    let (mut mbap, mut rtu_samples) = (vec![], vec![]);
    for _ in 0..ROUNDS {
        mbap.extend(samples(WARM, N / ROUNDS, |tid| tcp_read(&mut m, tid, 1)));
        rtu_samples.extend(samples(WARM, N / ROUNDS, &mut rtu_read));
    }
    gw.terminate(Duration::from_secs(5));
    let (a, b) = (spread(&mbap), spread(&rtu_samples));
    let mut t = String::from("| master | p50 | p99 | max |\n|---|---|---|---|\n");
    for (who, x) in [
        ("Modbus/TCP (mbap listener)", a),
        ("RTU over TCP (rtu listener)", b),
    ] {
        let _ = writeln!(
            t,
            "| {who} | {} | {} | {} |",
            us(x.p50),
            us(x.p99),
            us(x.max)
        );
    }
    let more = diff_us(a.p50, b.p50);
    r.row(
        "rtu-listener",
        "RTU-over-TCP master against a Modbus/TCP one, p50, FC 03 × 1",
        format!("{more:+.0} µs ({} → {})", us(a.p50), us(b.p50)),
        "≤ 50 µs",
        Some(more <= 50.0),
    );
    r.detail(
        &format!("RTU over TCP masters ({N} samples each, in {ROUNDS} rounds taking turns, each after {WARM} warm-up; the simulator on a pty as an RTU device, unpaced, the line at 4 000 000 baud)"),
        &command("rtu-listener"),
        &t,
    );
}

// ---------------------------------------------------------------------------------
// 9. RTU at the line's limit, side by side with mbusd

/// A gateway under test in the side-by-side RTU scenario: where masters connect, and
/// its process for the CPU it spends.
struct Contender {
    name: String,
    addr: std::net::SocketAddr,
    pid: u32,
    /// Keeps the line (pty pair and simulator) alive.
    _line: Line,
    _proc: ContenderProc,
}

enum ContenderProc {
    Mbgate(#[allow(dead_code)] Gateway),
    Mbusd(std::process::Child),
}

impl Drop for ContenderProc {
    fn drop(&mut self) {
        if let ContenderProc::Mbusd(c) = self {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// How late this machine wakes a thread sleeping on a timer: the gateway's own timer
/// ([`mbgate::port::serial::PreciseTimer`], a timerfd on tokio's reactor) set 1750 µs ahead
/// (t3.5 above 19 200 baud) 1000 times, on an otherwise idle runtime. A gateway keeps
/// the gap with one such wake more than a master talking straight to the device, so
/// this is the least it can add to a transaction without spinning.
fn timer_floor() -> Spread {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("a runtime");
    rt.block_on(async {
        let mut timer = mbgate::port::serial::PreciseTimer::new().expect("a timerfd");
        let mut late = Vec::new();
        for _ in 0..1000 {
            let at = tokio::time::Instant::now() + Duration::from_micros(1750);
            timer.until(at).await.expect("the timer");
            late.push(tokio::time::Instant::now() - at);
        }
        spread(&late)
    })
}

/// The line's limit with a fast device: pymodbus' own RTU server on a pty, unpaced (it
/// answers as fast as Python does, sooner than a request takes on a 115 200 baud
/// wire, which mbgate would take for a reply begun before its request left: the
/// line is set to 4 000 000 baud), the gap t3.5 = 1750 µs as at any speed above
/// 19 200 baud. Direct, through mbgate (the default gap, and `inter_frame_gap_us = 1000`)
/// and through mbusd `-R 1`, each on a pty pair and server of its own, in turns. The
/// target: mbgate's p50 at most t3.5 + 150 µs above the direct p50.
fn rtu_unpaced(r: &mut Report, round: Duration, rounds: usize, mbusd: Option<&Path>) -> String {
    const BAUD: u32 = 4_000_000;
    let t35 = Duration::from_micros(mbgate::frame::rtu::t35_us(BAUD, 10));
    eprintln!("rtu-limit: pymodbus RTU server, unpaced, FC 03 × 1");
    let mut paths = vec![
        mbgate_contender_on(Line::pymodbus_rtu(BAUD), "rtu", "mbgate", BAUD, &[]),
        mbgate_contender_on(
            Line::pymodbus_rtu(BAUD),
            "rtu",
            "mbgate, gap 1000 µs",
            BAUD,
            &["inter_frame_gap_us = 1000"],
        ),
    ];
    if let Some(m) = mbusd {
        paths.push(mbusd_contender_on(Line::pymodbus_rtu(BAUD), m, BAUD));
    }
    let direct_line = Line::pymodbus_rtu(BAUD);
    let LimitRows {
        direct,
        direct_gap,
        via,
    } = LimitRows::measure(&direct_line, &paths, 1, t35, round, rounds);
    let d = spread(&direct.times).p50;
    let cell = |p: &LimitRow| format!("{:.1} ({})", p.rate(), ms(spread(&p.times).p50));
    let above = |p: &LimitRow| spread(&p.times).p50.saturating_sub(d);
    let g = &via[0];
    let bound = t35 + Duration::from_micros(150);
    let (busd, ratio) = match paths.iter().position(|p| p.name.starts_with("mbusd")) {
        Some(i) => (
            format!("{} (+{})", cell(&via[i]), us(above(&via[i]))),
            format!("**{:.2}**", g.rate() / via[i].rate()),
        ),
        None => ("(MBUSD not set)".into(), "-".into()),
    };
    r.row(
        "rtu-limit",
        "RTU, pymodbus server unpaced: mbgate's p50 above direct",
        format!("{} (t3.5 = {})", us(above(g)), us(t35)),
        "≤ t3.5 + 150 µs",
        Some(above(g) <= bound),
    );
    format!(
        "A fast device: pymodbus' own RTU server (`tests/py/stock_server.py --framer rtu`), unpaced, the line set to {BAUD} baud (t3.5 = {}); tx/s (p50), and in brackets after it the p50 above direct:\n\n\
         | direct tx/s (p50) | mbgate tx/s (p50) | mbgate above direct, p50 | target | direct keeping t3.5 (p50 above direct) | mbgate CPU/tx | mbgate gap 1000 µs | mbusd -R 1 | mbgate / mbusd |\n|---|---|---|---|---|---|---|---|---|\n\
         | {} | {} | **{}** | ≤ {} | {} (+{}) | {} | {} (+{}) | {busd} | {ratio} |\n",
        us(t35),
        cell(&direct),
        cell(g),
        us(above(g)),
        us(bound),
        cell(&direct_gap),
        us(above(&direct_gap)),
        us(Duration::from_nanos(g.cpu_ns / g.times.len().max(1) as u64)),
        cell(&via[1]),
        us(above(&via[1])),
    )
}

/// The simulator as an RTU device paced at `baud` on a pty pair of its own.
fn rtu_sim_line(baud: u32) -> Line {
    serial_sim_line("rtu", baud)
}

/// An FC 03 read of `qty` registers of unit 1 in `framing` ("rtu" or "ascii").
fn serial_read(framing: &str, qty: u16) -> Vec<u8> {
    let pdu = [0x03, 0, 0, 0, qty as u8];
    match framing {
        "rtu" => mbgate::frame::rtu::encode(1, &pdu),
        _ => mbgate::frame::ascii::encode(1, &pdu),
    }
}

/// Bytes of the reply to [`serial_read`]: ASCII is `:`, two hex digits a byte of
/// unit, function, count, data and LRC, CR LF.
fn serial_reply_len(framing: &str, qty: u16) -> usize {
    match framing {
        "rtu" => rtu_reply_len(qty),
        _ => 3 + 2 * (4 + 2 * usize::from(qty)),
    }
}

/// The simulator as a paced device in `framing` at `baud` on a pty pair of its own.
fn serial_sim_line(framing: &str, baud: u32) -> Line {
    let speed = baud.to_string();
    Line::start_probed(
        &["--framing", framing, "--baud", &speed],
        &serial_read(framing, 1),
        serial_reply_len(framing, 1),
    )
}

/// `mbgate run` in RTU at `baud`, no flow control, with extra `[serial]` lines.
fn mbgate_contender(name: &str, baud: u32, serial: &[&str]) -> Contender {
    mbgate_contender_in("rtu", name, baud, serial)
}

/// [`mbgate_contender`] in `framing`.
fn mbgate_contender_in(framing: &str, name: &str, baud: u32, serial: &[&str]) -> Contender {
    mbgate_contender_on(serial_sim_line(framing, baud), framing, name, baud, serial)
}

/// [`mbgate_contender_in`] in front of the device on `line`.
fn mbgate_contender_on(
    line: Line,
    framing: &str,
    name: &str,
    baud: u32,
    serial: &[&str],
) -> Contender {
    let mut cfg = Cfg::new(&line.socat.gw)
        .serial(&format!("framing = {framing:?}"))
        .serial("flow_control = \"none\"")
        .serial(&format!("baud_rate = {baud}"));
    for l in serial {
        cfg = cfg.serial(l);
    }
    let gw = line.gateway_with(cfg, &[], &[]);
    Contender {
        name: name.into(),
        addr: gw.addr,
        pid: gw.proc.pid(),
        _line: line,
        _proc: ContenderProc::Mbgate(gw),
    }
}

/// mbusd (`MBUSD=/path/to/mbusd`) in front of the same simulator at `baud`, with its
/// pause between requests at its least (`-R 1`, 1 ms), no retries.
fn mbusd_contender(mbusd: &Path, baud: u32) -> Contender {
    mbusd_contender_on(rtu_sim_line(baud), mbusd, baud)
}

/// [`mbusd_contender`] in front of the device on `line`.
fn mbusd_contender_on(line: Line, mbusd: &Path, baud: u32) -> Contender {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port();
    let child = std::process::Command::new(mbusd)
        .args(["-d", "-L", "-", "-v", "0", "-p"])
        .arg(&line.socat.gw)
        .args(["-s", &baud.to_string(), "-m", "8N1", "-A", "127.0.0.1"])
        .args([
            "-P",
            &port.to_string(),
            "-R",
            "1",
            "-W",
            "500",
            "-N",
            "0",
            "-T",
            "0",
        ])
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("start mbusd");
    let addr = std::net::SocketAddr::from(([127, 0, 0, 1], port));
    let start = Instant::now();
    while TcpStream::connect(addr).is_err() {
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "mbusd never listened"
        );
        thread::sleep(Duration::from_millis(20));
    }
    Contender {
        name: "mbusd -R 1".into(),
        addr,
        pid: child.id(),
        _line: line,
        _proc: ContenderProc::Mbusd(child),
    }
}

/// One master polling FC 03 × `qty` for `budget`: each transaction's time.
fn poll_for(budget: Duration, mut f: impl FnMut(u16) -> Duration) -> Vec<Duration> {
    for tid in 0..8 {
        f(tid);
    }
    let start = Instant::now();
    let mut v = Vec::new();
    while start.elapsed() < budget && v.len() < MAX_TRANSACTIONS {
        v.push(f(v.len() as u16));
    }
    v
}

/// One master straight on the device's pty, polling with `req` (answered in `len`
/// bytes) for `round`, sleeping `gap` before each request (zero: none); each
/// transaction's time, the sleep included.
fn poll_direct(
    m: &mut RawLine,
    req: &[u8],
    len: usize,
    round: Duration,
    gap: Duration,
) -> Vec<Duration> {
    poll_for(round, |_| {
        let t = Instant::now();
        if !gap.is_zero() {
            thread::sleep(gap);
        }
        assert_eq!(m.transact(req, len).len(), len, "short reply");
        t.elapsed()
    })
}

/// One master polling FC 03 × `qty` through `p` for `round`: its transaction times and
/// the CPU `p` spent on them go into `out`.
fn poll_through(p: &Contender, qty: u16, round: Duration, out: &mut LimitRow) {
    let mut s = TcpStream::connect(p.addr).expect("connect");
    s.set_nodelay(true).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let cpu0 = cpu_ns(p.pid);
    let times = poll_for(round, |tid| tcp_read(&mut s, tid, qty));
    out.cpu_ns += cpu_ns(p.pid) - cpu0;
    out.times.extend(times);
}

/// The paths of one RTU row of the line's limit.
struct LimitRows {
    /// A master straight on the device's pty.
    direct: LimitRow,
    /// The same master keeping the gap itself after each reply, on a sleep as precise
    /// as the gateway's timer: what a transaction takes on this machine when the line
    /// is left silent for the gap, whoever keeps it.
    direct_gap: LimitRow,
    /// A master through each of the paths, in their order.
    via: Vec<LimitRow>,
}

impl LimitRows {
    /// FC 03 × `qty` polled on each path in turn for `round`, `rounds` times: straight
    /// on `device`'s pty, the same keeping `gap`, then through each of `paths`.
    fn measure(
        device: &Line,
        paths: &[Contender],
        qty: u16,
        gap: Duration,
        round: Duration,
        rounds: usize,
    ) -> LimitRows {
        let (req, len) = (serial_read("rtu", qty), serial_reply_len("rtu", qty));
        let mut rows = LimitRows {
            direct: LimitRow::default(),
            direct_gap: LimitRow::default(),
            via: vec![LimitRow::default(); paths.len()],
        };
        for _ in 0..rounds {
            let mut m = device.raw();
            let direct = poll_direct(&mut m, &req, len, round, Duration::ZERO);
            rows.direct.times.extend(direct);
            let kept = poll_direct(&mut m, &req, len, round, gap);
            rows.direct_gap.times.extend(kept);
            drop(m);
            for (p, out) in paths.iter().zip(rows.via.iter_mut()) {
                poll_through(p, qty, round, out);
            }
        }
        rows
    }
}

/// Per path of one row: transaction times, and CPU nanoseconds spent on them.
#[derive(Default, Clone)]
struct LimitRow {
    times: Vec<Duration>,
    cpu_ns: u64,
}

impl LimitRow {
    fn rate(&self) -> f64 {
        self.times.len() as f64 / self.times.iter().sum::<Duration>().as_secs_f64()
    }
}

/// The line's own limit, side by side: the simulator as a paced RTU device at 9600 to
/// 921 600 baud, one master polling FC 03 × 1 and × 10 as fast as answered, straight on
/// the pty (the device's pace and turnaround), through mbgate (the default gap, t3.5
/// of Modbus over Serial Line V1.02 §2.5.1.1, and above 19 200 baud also with
/// `inter_frame_gap_us = 1000`) and, given `MBUSD=/path/to/mbusd`, through mbusd
/// `-R 1`; each path on a pty pair and simulator of its own, the paths taking turns
/// (A B A B) for `MBGATE_BENCH_RTU_ROUND_MS` (default 1000) each
/// (`MBGATE_BENCH_RTU_BAUDS` picks speeds). The limit: the
/// direct transaction time plus exactly the gap.
fn rtu_limit(r: &mut Report) {
    const ROUNDS: usize = 2;
    // The master's own sleeps as precise as a timerfd: no 50 µs of timer slack.
    // SAFETY: PR_SET_TIMERSLACK takes a number and changes only this thread's slack.
    #[allow(unsafe_code)]
    unsafe {
        libc::prctl(libc::PR_SET_TIMERSLACK, 1 as libc::c_ulong);
    }
    let round = Duration::from_millis(
        std::env::var("MBGATE_BENCH_RTU_ROUND_MS")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(1000),
    );
    let mbusd = std::env::var_os("MBUSD").map(std::path::PathBuf::from);
    if mbusd.is_none() {
        eprintln!("rtu-limit: MBUSD not set: the mbusd column is skipped (MBUSD=/path/to/mbusd)");
    }
    let mut t = String::from(
        "| baud | registers | direct tx/s (p50) | limit with t3.5 | mbgate tx/s (p50) | mbgate / limit | mbgate p50 − direct p50 − t3.5 | direct keeping t3.5 tx/s (p50) | mbgate / it | mbgate CPU/tx | mbgate gap 1000 µs tx/s (p50) | mbusd -R 1 tx/s (p50) | mbgate / mbusd | mbusd CPU/tx |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    // `MBGATE_BENCH_RTU_BAUDS=115200,921600` measures only those speeds.
    let bauds: Vec<u32> = std::env::var("MBGATE_BENCH_RTU_BAUDS")
        .ok()
        .map(|v| v.split(',').filter_map(|b| b.trim().parse().ok()).collect())
        .unwrap_or_else(|| vec![9600, 19_200, 115_200, 921_600]);
    for baud in bauds {
        let t35 = Duration::from_micros(mbgate::frame::rtu::t35_us(baud, 10));
        let mut paths = vec![mbgate_contender("mbgate", baud, &[])];
        if baud > 19_200 {
            paths.push(mbgate_contender(
                "mbgate, gap 1000 µs",
                baud,
                &["inter_frame_gap_us = 1000"],
            ));
        }
        if let Some(m) = &mbusd {
            paths.push(mbusd_contender(m, baud));
        }
        let direct_line = rtu_sim_line(baud);
        for qty in [1u16, 10] {
            eprintln!("rtu-limit: {baud} baud, FC 03 × {qty}");
            let LimitRows {
                direct,
                direct_gap,
                via,
            } = LimitRows::measure(&direct_line, &paths, qty, t35, round, ROUNDS);
            let d = spread(&direct.times);
            let per_direct = 1.0 / direct.rate();
            let limit = 1.0 / (per_direct + t35.as_secs_f64());
            let cell = |p: &LimitRow| format!("{:.1} ({})", p.rate(), ms(spread(&p.times).p50));
            let cpu = |p: &LimitRow| {
                // The warm-up transactions are not in `times`: slightly high.
                us(Duration::from_nanos(p.cpu_ns / p.times.len().max(1) as u64))
            };
            let g = &via[0];
            let gap = paths
                .iter()
                .position(|p| p.name.contains("gap"))
                .map_or("-".into(), |i| cell(&via[i]));
            let busd = paths.iter().position(|p| p.name.starts_with("mbusd"));
            let (busd_cell, ratio, busd_cpu) = match busd {
                Some(i) => (
                    cell(&via[i]),
                    format!("**{:.2}**", g.rate() / via[i].rate()),
                    cpu(&via[i]),
                ),
                None => ("(MBUSD not set)".into(), "-".into(), "-".into()),
            };
            let _ = writeln!(
                t,
                "| {baud} | {qty} | {:.1} ({}) | {limit:.1}/s | {} | **{}** | {:+.1} µs | {} | {} | {} | {gap} | {busd_cell} | {ratio} | {busd_cpu} |",
                direct.rate(),
                ms(d.p50),
                cell(g),
                pct(g.rate() / limit),
                diff_us(d.p50 + t35, spread(&g.times).p50),
                cell(&direct_gap),
                pct(g.rate() / direct_gap.rate()),
                cpu(g),
            );
            r.row(
                "rtu-limit",
                &format!("RTU {baud} baud FC 03 × {qty}: mbgate against the line's limit (direct + t3.5)"),
                format!("{:.1}/s of {limit:.1}/s = {}", g.rate(), pct(g.rate() / limit)),
                "≥ 98 %",
                Some(g.rate() >= 0.98 * limit),
            );
        }
    }
    let unpaced = rtu_unpaced(r, round, ROUNDS, mbusd.as_deref());
    let _ = write!(t, "\n{unpaced}");
    // ASCII: its limit is the wire time alone (no gap between frames).
    let mut a = String::from(
        "| baud | registers | direct tx/s (p50) | mbgate tx/s (p50) | mbgate / direct | mbgate CPU/tx |\n|---|---|---|---|---|---|\n",
    );
    for baud in [9600u32, 115_200] {
        let gw = mbgate_contender_in("ascii", "mbgate ascii", baud, &[]);
        let direct_line = serial_sim_line("ascii", baud);
        let qty = 1;
        eprintln!("rtu-limit: ASCII {baud} baud, FC 03 × {qty}");
        let req = serial_read("ascii", qty);
        let len = serial_reply_len("ascii", qty);
        let (mut direct, mut via) = (LimitRow::default(), LimitRow::default());
        for _ in 0..ROUNDS {
            let mut m = direct_line.raw();
            direct
                .times
                .extend(poll_direct(&mut m, &req, len, round, Duration::ZERO));
            drop(m);
            poll_through(&gw, qty, round, &mut via);
        }
        let ratio = via.rate() / direct.rate();
        let _ = writeln!(
            a,
            "| {baud} | {qty} | {:.1} ({}) | {:.1} ({}) | **{}** | {} |",
            direct.rate(),
            ms(spread(&direct.times).p50),
            via.rate(),
            ms(spread(&via.times).p50),
            pct(ratio),
            us(Duration::from_nanos(
                via.cpu_ns / via.times.len().max(1) as u64
            )),
        );
        r.row(
            "rtu-limit",
            &format!("ASCII {baud} baud FC 03 × {qty}: mbgate against the line's limit (direct)"),
            format!(
                "{:.1}/s of {:.1}/s = {}",
                via.rate(),
                direct.rate(),
                pct(ratio)
            ),
            "≥ 98 %",
            Some(ratio >= 0.98),
        );
    }
    let _ = write!(t, "\nASCII (the same, `--framing ascii`; no gap between frames, so the limit is the direct rate):\n\n{a}");
    let note = if mbusd.is_some() {
        ""
    } else {
        "\nmbusd not measured: run with `MBUSD=/path/to/mbusd` (built from github.com/3cky/mbusd with cmake).\n"
    };
    let floor = timer_floor();
    let _ = write!(
        t,
        "\nThis machine's timer floor (a timerfd set 1750 µs ahead, 1000 times, on an idle runtime): late by {} at p50, {} at p99. The gap costs a gateway one such wake more than a master talking straight to the device.\n",
        us(floor.p50),
        us(floor.p99),
    );
    r.detail(
        &format!("RTU at the line's limit (the simulator paced as a UART, 10 bits a byte; one master polling; each path on its own pty pair and simulator; paths in turn, {ROUNDS} rounds of {round:?} each; p50 of the transaction time in brackets)"),
        "MBUSD=/path/to/mbusd cargo bench --bench gateway -- rtu-limit",
        &format!("{t}{note}"),
    );
}

// ---------------------------------------------------------------------------------
// The capture's cost

/// What a capture costs the line (docs/capture.md "Never in the line's way"): one
/// master pipelining FC 03 × 1 (window 4, `max_in_flight = 4`) through the gateway
/// to the simulator on a pty paced as a 4 Mbaud line, with no capture; with `mbgate
/// capture -o -` into a pipe nobody reads (as `mbgate capture -o - | sleep 60`: the
/// pipe fills, the capture drops and counts, the line must not notice); and with
/// `mbgate capture -o /dev/null` (every packet built, encoded and written). In rounds
/// that take turns; throughput and CPU per transaction, each against none; the
/// packets each capture dropped, as `mbgate capture` reports them.
fn capture_cost(r: &mut Report) {
    eprintln!("capture: throughput with no capture, a reader that never reads, /dev/null");
    const BUDGET: Duration = Duration::from_secs(3);
    const ROUNDS: usize = 3;
    const CASES: [(&str, Option<&str>); 3] = [
        ("none", None),
        ("`-o -` into a pipe never read", Some("-")),
        ("`-o /dev/null`", Some("/dev/null")),
    ];
    let line = Line::start(&["--baud", "4000000", "--pipeline"]);
    let socket = line.dir.path().join("control.sock");
    let mut rate = [0f64; CASES.len()];
    let mut cpu = [0u64; CASES.len()];
    let mut transactions = [0u64; CASES.len()];
    let mut packets = [0u64; CASES.len()];
    let mut dropped = [0u64; CASES.len()];
    for _ in 0..ROUNDS {
        for (i, (_, output)) in CASES.into_iter().enumerate() {
            let cfg = Cfg::new(&line.socat.gw)
                .serial("baud_rate = 4000000")
                .serial("silence_floor_ms = 0")
                .control(&format!("socket = {:?}", socket.display().to_string()));
            let mut gw = line.gateway_with(cfg, &["max_in_flight = 4"], &[]);
            gw.wait_log("control socket", Duration::from_secs(5));
            let client = output.map(|out| {
                let args = ["capture", "--socket", socket.to_str().unwrap(), "-o", out];
                let (mut cmd, stderr) = Launch::default().command(args);
                let mut child = cmd.spawn().expect("mbgate capture");
                drop(cmd);
                // Its standard output is a pipe this never reads (for /dev/null, unused).
                let stdout = child.stdout.take();
                (child, stdout, stderr)
            });
            // The capture is running once the gateway says so.
            if client.is_some() {
                wait_for("the capture", Duration::from_secs(5), || {
                    gw.log().contains("capture started")
                });
            }
            let mut s = connect(&gw);
            let pid = gw.proc.pid();
            let cpu0 = cpu_ns(pid);
            let got = tcp_throughput(&mut s, 4, 1, BUDGET);
            cpu[i] += cpu_ns(pid) - cpu0;
            rate[i] += got / ROUNDS as f64;
            transactions[i] += (got * BUDGET.as_secs_f64()) as u64;
            if let Some((mut child, stdout, mut stderr)) = client {
                // The reader goes away (as `sleep 60` ends): the capture's output
                // fails, it stops the capture and says what it dropped. /dev/null
                // never fails: Ctrl-C ends that one.
                drop(stdout);
                if output == Some("/dev/null") {
                    let _ = Command::new("kill")
                        .args(["-INT", &child.id().to_string()])
                        .status();
                }
                let start = Instant::now();
                while child.try_wait().unwrap().is_none() {
                    assert!(
                        start.elapsed() < Duration::from_secs(10),
                        "mbgate capture did not end"
                    );
                    thread::sleep(Duration::from_millis(10));
                }
                let mut err = String::new();
                std::io::Read::read_to_string(&mut stderr, &mut err).unwrap();
                let number = |after: &str| -> u64 {
                    err.split(after)
                        .next()
                        .and_then(|head| head.split_whitespace().last())
                        .and_then(|n| n.parse().ok())
                        .unwrap_or_else(|| panic!("no \"{after}\" in: {err}"))
                };
                packets[i] += number(" packets");
                if !err.contains("none dropped") {
                    dropped[i] += number(" dropped");
                }
            }
            gw.terminate(Duration::from_secs(5));
        }
    }
    let per = |i: usize| Duration::from_nanos(cpu[i] / transactions[i].max(1));
    let mut t = String::from(
        "| capture | transactions/s | CPU per transaction | packets captured | packets dropped (counted, reported) |\n|---|---|---|---|---|\n",
    );
    for (i, (name, _)) in CASES.into_iter().enumerate() {
        let _ = writeln!(
            t,
            "| {name} | {:.0} | {} | {} | {} |",
            rate[i],
            us(per(i)),
            packets[i],
            dropped[i]
        );
    }
    for (i, (name, _)) in CASES.into_iter().enumerate().skip(1) {
        let change = (rate[i] / rate[0] - 1.0) * 100.0;
        r.row(
            "capture",
            &format!("capture {name}: throughput against none, FC 03 × 1, window 4"),
            format!("{change:+.1} % ({:.0} → {:.0}/s)", rate[0], rate[i]),
            "> -5 %",
            Some(change > -5.0),
        );
        r.row(
            "capture",
            &format!("capture {name}: packets dropped, as mbgate capture reports them"),
            format!("{} of {}", dropped[i], dropped[i] + packets[i]),
            "counted",
            None,
        );
    }
    r.detail(
        &format!("The capture's cost (a 4 Mbaud pty, the simulator pipelining; {ROUNDS} rounds of {BUDGET:?} a case, taking turns)"),
        &command("capture"),
        &t,
    );
}
