//! `capture`: what a running capture (`mbgate capture`) costs the line, in throughput
//! and CPU per transaction, against none.

use super::common::{cpu_ns, wait_for, Cfg, Launch};
use super::report::{command, us, Report};
use super::shared::{connect, tcp_throughput, Line};
use std::fmt::Write as _;
use std::process::Command;
use std::thread;
use std::time::{Duration, Instant};

/// What a capture costs the line (docs/capture.md "Never in the line's way"): one
/// master pipelining FC 03 × 1 (window 4, `max_in_flight = 4`) through the gateway
/// to the simulator on a pty paced as a 4 Mbaud line, with no capture; with `mbgate
/// capture -o -` into a pipe nobody reads (as `mbgate capture -o - | sleep 60`: the
/// pipe fills, the capture drops and counts, the line must not notice); and with
/// `mbgate capture -o /dev/null` (every packet built, encoded and written). In rounds
/// that take turns; throughput and CPU per transaction, each against none; the
/// packets each capture dropped, as `mbgate capture` reports them.
pub(super) fn capture_cost(r: &mut Report) {
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
