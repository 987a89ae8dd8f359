//! `wire`: wire efficiency: transactions a second through mbgate against what the
//! wire allows, one master polling or pipelining, at 9600, 19 200 and 115 200 baud.

use super::common::sim::RawLine;
use super::report::{command, pct, Report};
use super::shared::{connect, reply_len, tcp_throughput, throughput, wire_limit, Line};
use std::fmt::Write as _;
use std::time::Duration;

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

pub(super) fn wire(r: &mut Report) {
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
            // Every request its own transaction: the master sends the same read, which
            // coalescing would answer with fewer transactions than requests (measured
            // on its own, `-- coalesce`).
            let gw = line.gateway(&[&inf, "coalesce = false"], &[]);
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
