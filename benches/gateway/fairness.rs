//! `fairness`: 1, 10 and 100 masters polling at once, and a poller beside a master
//! pipelining 16: throughput, each master's share and the p99 latency.

use super::common::{read_frame, Gateway};
use super::report::{command, ms, pct, spread, Report};
use super::shared::{
    connect, peak_rss_row, proc_status, tcp_read, throughput, wire_limit, Line, MAX_TRANSACTIONS,
};
use std::fmt::Write as _;
use std::io::Write as _;
use std::net::TcpStream;
use std::sync::{Arc, Barrier};
use std::thread;
use std::time::{Duration, Instant};

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

pub(super) fn fairness(r: &mut Report) {
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
