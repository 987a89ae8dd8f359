//! One master through mbgate against the same master through a plain TCP-to-serial
//! byte pipe (socat), what a single-master user of the CIE-M10 would run instead: the
//! same pty pair and the same device, turn about (A B A B), FC 03 of 1 and of 10
//! registers, polled one at a time, at 9600 and 115 200 baud. mbgate with its default
//! settings (a lone reply taken at once: nothing can follow it), and again with
//! `device_notifications = true` (every reply held until a pause confirms it). Target:
//! 0.95 × the pipe at every row of the defaults, no wrong reply anywhere
//! (docs/performance.md, "One master against a byte pipe").
//!
//! The device is mbgate's simulator with `--baud` (generic unit 1, each register
//! holding its address), which paces its bytes as a UART at that speed would (both
//! ways: a request is read once its last byte would have arrived, a reply leaves a
//! byte at a time): on a pty, nothing else would. Both paths talk to that one device.
//!
//! `cargo bench --bench pipe`; `MBGATE_BENCH_TURN_MS` sets each turn's length (2000),
//! `MBGATE_BENCH_MD=FILE` writes the table to FILE too. Everything on 127.0.0.1; each
//! turn is bounded in time and count.

#[path = "../tests/common/mod.rs"]
mod common;

use common::sim::{generic_flags, RawLine};
use common::{read_frame, read_reply, read_req, socat_pipe, tempdir, Cfg, Gateway, Proc, Socat};
use std::fmt::Write as _;
use std::io::Write as _;
use std::net::TcpStream;
use std::time::{Duration, Instant};

/// Upper bound on transactions in one turn, whatever its length.
const MAX_TRANSACTIONS: usize = 100_000;

/// What one turn measured.
#[derive(Default, Clone, Copy)]
struct Turn {
    done: usize,
    wrong: usize,
    took: Duration,
}

impl Turn {
    fn rate(&self) -> f64 {
        self.done as f64 / self.took.as_secs_f64()
    }
}

/// Polls FC 03 reads of `qty` registers at address 0 over `s` for `budget`: each reply
/// must carry its own id and the registers' addresses as values, or it counts wrong.
fn poll(s: &mut TcpStream, qty: u16, budget: Duration) -> Turn {
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    s.set_nodelay(true).unwrap();
    let values: Vec<u16> = (0..qty).collect();
    // Warm up: the first exchanges open ports and fill caches.
    for tid in 0..5u16 {
        s.write_all(&read_req(tid, 1, 0, qty)).unwrap();
        read_frame(s);
    }
    let mut turn = Turn::default();
    let start = Instant::now();
    let mut tid = 100u16;
    while start.elapsed() < budget && turn.done < MAX_TRANSACTIONS {
        tid = tid.wrapping_add(1).max(100);
        s.write_all(&read_req(tid, 1, 0, qty)).unwrap();
        let reply = read_frame(s);
        if reply != read_reply(tid, 1, &values) {
            turn.wrong += 1;
        }
        turn.done += 1;
    }
    turn.took = start.elapsed();
    turn
}

/// One pty pair and the paced simulator on it.
struct Line {
    dir: tempfile::TempDir,
    socat: Socat,
    _sim: Proc,
}

impl Line {
    fn start(baud: u32) -> Line {
        let dir = tempdir();
        let socat = Socat::start(dir.path());
        let speed = baud.to_string();
        let mut args = vec!["sim", "--serial", socat.dev.to_str().unwrap()];
        args.extend(generic_flags("mbap", "1", &speed));
        args.extend(["--registers", "200", "--log-level", "warn"]);
        let sim = Proc::start(&args, "");
        // Answered once: the simulator is serving.
        let mut probe = RawLine::open(&socat.gw);
        let since = Instant::now();
        while probe.transact(&read_req(1, 1, 0, 1), 11).len() < 11 {
            assert!(
                since.elapsed() < Duration::from_secs(20),
                "the simulator never answered"
            );
        }
        Line {
            dir,
            socat,
            _sim: sim,
        }
    }

    /// A turn through the byte pipe.
    fn through_pipe(&self, qty: u16, budget: Duration) -> Turn {
        let (mut child, addr) = socat_pipe(&self.socat.gw);
        let mut s = TcpStream::connect(addr).expect("connect to socat");
        let turn = poll(&mut s, qty, budget);
        drop(s);
        let _ = child.kill();
        let _ = child.wait();
        turn
    }

    /// A turn through mbgate at `baud` with its defaults and `relay` lines.
    fn through_gateway(&self, baud: u32, relay: &[&str], qty: u16, budget: Duration) -> Turn {
        let mut cfg = Cfg::new(&self.socat.gw)
            .serial(&format!("baud_rate = {baud}"))
            .log_level("info");
        for l in relay {
            cfg = cfg.relay(l);
        }
        let mut gw = Gateway::start(&cfg, self.dir.path());
        let mut s = gw.connect();
        let turn = poll(&mut s, qty, budget);
        drop(s);
        gw.terminate(Duration::from_secs(10));
        turn
    }
}

fn main() {
    let budget = Duration::from_millis(
        std::env::var("MBGATE_BENCH_TURN_MS")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(2000),
    );
    let load_before = loadavg();
    let mut t = String::from(
        "| baud | registers | mbgate | pipe tx/s (A, A) | mbgate tx/s (B, B) | mbgate / pipe | wrong (pipe, mbgate) | target ≥ 0.95 |\n|---|---|---|---|---|---|---|---|\n",
    );
    for baud in [9600u32, 115_200] {
        let line = Line::start(baud);
        for (name, relay) in [
            ("defaults", &[][..]),
            (
                "device_notifications = true",
                &["device_notifications = true"][..],
            ),
        ] {
            for qty in [1u16, 10] {
                eprintln!("pipe: {baud} baud, FC 03 x {qty}, mbgate {name}");
                let mut turns = Vec::new();
                for _ in 0..2 {
                    turns.push((
                        line.through_pipe(qty, budget),
                        line.through_gateway(baud, relay, qty, budget),
                    ));
                }
                let rate = |f: fn(&(Turn, Turn)) -> Turn| -> Vec<f64> {
                    turns.iter().map(|p| f(p).rate()).collect()
                };
                let (a, b) = (rate(|p| p.0), rate(|p| p.1));
                let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
                let ratio = mean(&b) / mean(&a);
                let wrong_a: usize = turns.iter().map(|p| p.0.wrong).sum();
                let wrong_b: usize = turns.iter().map(|p| p.1.wrong).sum();
                let target = match name {
                    "defaults" if ratio >= 0.95 && wrong_a + wrong_b == 0 => "met",
                    "defaults" => "**not met**",
                    _ => "(reported)",
                };
                let _ = writeln!(
                    t,
                    "| {baud} | {qty} | {name} | {:.1}, {:.1} | {:.1}, {:.1} | {ratio:.3} | {wrong_a}, {wrong_b} | {target} |",
                    a[0], a[1], b[0], b[1]
                );
                eprintln!("  pipe {a:.1?} mbgate {b:.1?}: {ratio:.3}");
            }
        }
    }
    let md = format!(
        "#### One master against a byte pipe\n\n`cargo bench --bench pipe` (turns of {} ms, A B A B; load average (1, 5, 15 min) at start {load_before}, at end {}). The device: `mbgate sim --baud BAUD --profile generic --fill address` on a socat pty pair, paced as a UART; the pipe: `socat TCP-LISTEN FILE:pty,raw`; the master polls FC 03 at address 0, one request at a time, checking every value.\n\n{t}",
        budget.as_millis(),
        loadavg()
    );
    println!("{md}");
    if let Some(path) = std::env::var_os("MBGATE_BENCH_MD") {
        std::fs::write(&path, &md).expect("write MBGATE_BENCH_MD");
    }
}

fn loadavg() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|l| l.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "?".into())
}
