//! `latency`: the latency mbgate adds to a transaction, against the simulator straight
//! on the pty and a bare socat byte pipe, and the CPU each of the two spends on one
//! (docs/performance.md "What a transaction costs": mbgate within 10 µs of the pipe at
//! p50 and 50 µs at p99, and no more CPU than socat).

use super::common::sim::RawLine;
use super::common::{cpu_ns, read_req};
use super::report::{command, diff_us, spread, us, Report};
use super::shared::{byte_pipe, connect, reply_len, samples, tcp_read, Line};
use std::fmt::Write as _;
use std::time::{Duration, Instant};

/// One FC 03 round trip straight to the simulator on the pty.
fn raw_read(m: &mut RawLine, tid: u16, qty: u16) -> Duration {
    let req = read_req(tid, 1, 0, qty);
    let t = Instant::now();
    let reply = m.transact(&req, reply_len(qty));
    let took = t.elapsed();
    assert_eq!(reply.len(), reply_len(qty), "short reply: {reply:02X?}");
    took
}

pub(super) fn latency(r: &mut Report) {
    eprintln!("latency: FC 03 straight to the simulator, then through mbgate");
    const WARM: usize = 200;
    const N: usize = 4000;
    // The three paths take turns, ROUNDS times, so a change in the machine's load
    // during the run falls on all of them alike; the pipe and mbgate swap places each
    // round, so neither always runs right after the other.
    const ROUNDS: usize = 8;
    let line = Line::start(&[]);
    let (mut direct, mut piped, mut through) = (vec![vec![]; 2], vec![vec![]; 2], vec![vec![]; 2]);
    let (mut cpu, mut transactions) = (0, 0);
    let (mut pipe_cpu, mut pipe_transactions) = (0, 0);
    // Each round's CPU a transaction, mbgate's over the pipe's.
    let mut round_ratios = Vec::with_capacity(ROUNDS);
    for round in 0..ROUNDS {
        let mut m = line.raw();
        for (i, qty) in [1, 10].into_iter().enumerate() {
            direct[i].extend(samples(WARM, N / ROUNDS, |tid| raw_read(&mut m, tid, qty)));
        }
        drop(m);
        let per_round = 2 * (WARM + N / ROUNDS);
        let mut via_pipe = || {
            let (mut pipe, mut s) = byte_pipe(&line);
            let cpu0 = cpu_ns(pipe.id());
            for (i, qty) in [1, 10].into_iter().enumerate() {
                piped[i].extend(samples(WARM, N / ROUNDS, |tid| tcp_read(&mut s, tid, qty)));
            }
            let spent = cpu_ns(pipe.id()) - cpu0;
            let _ = pipe.kill();
            let _ = pipe.wait();
            spent
        };
        let mut via_mbgate = || {
            let mut gw = line.gateway(&[], &[]);
            let mut s = connect(&gw);
            let cpu0 = cpu_ns(gw.proc.pid());
            for (i, qty) in [1, 10].into_iter().enumerate() {
                through[i].extend(samples(WARM, N / ROUNDS, |tid| tcp_read(&mut s, tid, qty)));
            }
            let spent = cpu_ns(gw.proc.pid()) - cpu0;
            gw.terminate(Duration::from_secs(5));
            spent
        };
        let (p, g) = if round % 2 == 0 {
            let p = via_pipe();
            (p, via_mbgate())
        } else {
            let g = via_mbgate();
            (via_pipe(), g)
        };
        pipe_cpu += p;
        pipe_transactions += per_round;
        cpu += g;
        transactions += per_round;
        round_ratios.push(g as f64 / p as f64);
    }
    round_ratios.sort_by(f64::total_cmp);
    // What mbgate itself spends on a transaction, against what it adds to one.
    let per = Duration::from_nanos(cpu) / transactions as u32;
    let pipe_per = Duration::from_nanos(pipe_cpu) / pipe_transactions as u32;
    let ratio = per.as_secs_f64() / pipe_per.as_secs_f64();
    r.row(
        "latency",
        "CPU time per transaction (schedstat), mbgate / socat",
        format!(
            "{ratio:.2} ({} / {}; rounds {:.2} to {:.2}, median {:.2})",
            us(per),
            us(pipe_per),
            round_ratios[0],
            round_ratios[ROUNDS - 1],
            (round_ratios[ROUNDS / 2 - 1] + round_ratios[ROUNDS / 2]) / 2.0
        ),
        "≤ 1.0",
        Some(ratio <= 1.0),
    );
    let mut t = String::from("| registers | path | p50 | p99 | max |\n|---|---|---|---|---|\n");
    for (i, qty) in [1u16, 10].into_iter().enumerate() {
        let (d, p, g) = (spread(&direct[i]), spread(&piped[i]), spread(&through[i]));
        for (path, x) in [
            ("pty → sim (direct)", d),
            ("TCP → socat (a bare byte pipe) → pty → sim", p),
            ("TCP → mbgate → pty → sim", g),
        ] {
            let _ = writeln!(t, "| {qty} | {path} | {} |", x.cells());
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
            "| {qty} | **added by mbgate** (a lone reply nothing can follow is taken at once) | **{a50:.0} µs** | **{a99:.0} µs** | |",
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
        for (q, pipe, through, target) in [("p50", p.p50, g.p50, 10.0), ("p99", p.p99, g.p99, 50.0)]
        {
            let above = diff_us(pipe, through);
            r.row(
                "latency",
                &format!("mbgate above the byte pipe, {q}, FC 03 × {qty}"),
                format!("{above:.0} µs ({} → {})", us(pipe), us(through)),
                &format!("≤ {target:.0} µs"),
                Some(above <= target),
            );
        }
    }
    r.detail(
        &format!("Added latency ({N} samples a path and size, in {ROUNDS} rounds in which the paths take turns, each after {WARM} warm-up; simulator unpaced, no delay; every path crosses the one socat hop of the pty pair)"),
        &command("latency"),
        &t,
    );
}
