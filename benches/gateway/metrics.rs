//! `metrics`: what the metrics listener and the status page cost the relay, in CPU per
//! transaction and round trips, against the metrics off.

use super::common::{cpu_ns, Cfg};
use super::report::{command, spread, us, Report};
use super::shared::{connect, samples, tcp_read, Line};
use std::fmt::Write as _;
use std::io::Write as _;
use std::net::TcpStream;
use std::sync::Arc;
use std::thread;
use std::time::Duration;

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
/// and round trips, each against off. The CPU is judged by the median of the rounds'
/// own ratios (each case against off in the same round, the cases' order turned every
/// other round), which a slow spell of the machine moves far less than the sums do.
/// The counters themselves are kept in every case.
pub(super) fn metrics_cost(r: &mut Report) {
    eprintln!("metrics: the same polling with the metrics listener off and on");
    const WARM: usize = 200;
    const N: usize = 24_000;
    const ROUNDS: usize = 12;
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
    // Each round's CPU a transaction, by case.
    let mut per_round = vec![[0f64; CASES.len()]; ROUNDS];
    for (k, round) in per_round.iter_mut().enumerate() {
        // Every other round the other way round, so that no case always comes first.
        let mut order: Vec<usize> = (0..CASES.len()).collect();
        if k % 2 == 1 {
            order.reverse();
        }
        for i in order {
            let (_, on, page) = CASES[i];
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
                let scrape = move || {
                    assert!(http_get(&addr, "/metrics") > 1000);
                    if page {
                        assert!(http_get(&addr, "/status.json") > 100);
                    }
                };
                // The first scrape (it opens the page) before the count starts, and
                // the next ones a second apart from a point that moves round by round
                // through the second: a round (about half a second) has as many
                // scrapes on average as a second of polling has, not one more at its
                // start.
                scrape();
                let phase = Duration::from_secs(1) * ((k * 5) % ROUNDS) as u32 / ROUNDS as u32;
                thread::spawn(move || {
                    let mut next = std::time::Instant::now() + phase;
                    while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                        let now = std::time::Instant::now();
                        if now >= next {
                            scrape();
                            next += Duration::from_secs(1);
                        } else {
                            thread::sleep((next - now).min(Duration::from_millis(50)));
                        }
                    }
                })
            });
            let mut s = connect(&gw);
            let pid = gw.proc.pid();
            let (cpu0, relay0) = (cpu_ns(pid), main_thread_cpu_ns(pid));
            lat[i].extend(samples(WARM, N / ROUNDS, |tid| tcp_read(&mut s, tid, 1)));
            let spent = cpu_ns(pid) - cpu0;
            cpu[i] += spent;
            round[i] = spent as f64 / (WARM + N / ROUNDS) as f64;
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
            "| {name} | {} | {} | {} |",
            us(per(&cpu, i)),
            us(per(&relay_cpu, i)),
            x.cells()
        );
    }
    let off = spread(&lat[0]);
    for (i, (name, _, _)) in CASES.into_iter().enumerate().skip(1) {
        let pct = |a: f64, b: f64| (b / a - 1.0) * 100.0;
        let (a, b) = (per(&cpu, 0), per(&cpu, i));
        let mut ratios: Vec<f64> = per_round.iter().map(|c| c[i] / c[0]).collect();
        ratios.sort_by(f64::total_cmp);
        let median = (ratios[(ROUNDS - 1) / 2] + ratios[ROUNDS / 2]) / 2.0;
        let cpu_pct = (median - 1.0) * 100.0;
        r.row(
            "metrics",
            &format!("metrics {name}: CPU per transaction against off (median of {ROUNDS} rounds)"),
            format!(
                "{cpu_pct:+.1} % (rounds {:+.1} to {:+.1} %; in all {} → {})",
                (ratios[0] - 1.0) * 100.0,
                (ratios[ROUNDS - 1] - 1.0) * 100.0,
                us(a),
                us(b)
            ),
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
