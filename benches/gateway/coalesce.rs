//! `coalesce`: many masters, one read (docs/masters.md, "Many masters, one read"):
//! many masters polling the same registers and different ones, with coalescing on and
//! off, and readers beside a writer.

use super::common;
use super::common::{cpu_ns, read_frame, read_reply, read_req, write_req, Cfg, Gateway, Launch};
use super::report::{command, pct, us, Report};
use super::shared::{reply_len, Line, MAX_TRANSACTIONS, REQ};
use std::fmt::Write as _;
use std::io::Write as _;
use std::net::TcpStream;
use std::path::Path;
use std::sync::atomic::{AtomicU16, Ordering};
use std::sync::{Arc, Barrier};
use std::thread;
use std::time::{Duration, Instant};

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

pub(super) fn coalesce(r: &mut Report) {
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
