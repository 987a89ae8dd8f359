//! `units`: what learned timeouts and priority classes cost, in CPU per transaction
//! and round trips: two masters polling FC 03 × 1 through the gateway, on one line
//! with the line's timeout and one class; with every unit's timeout learned
//! (`[[line.unit]] response_timeout_ms = "auto"`); and with the two masters on
//! listeners of priority 1 and 0.

use super::common::{cpu_ns, Gateway, Launch};
use super::report::{command, spread, us, Report};
use super::shared::{tcp_read, Line};
use std::fmt::Write as _;
use std::net::{SocketAddr, TcpStream};
use std::thread;
use std::time::Duration;

/// The configuration of a case: the line, its unit tables, its listeners.
fn config(gw: &std::path::Path, learned: bool, classes: bool) -> String {
    let mut text = format!(
        "[[line]]\nserial = {{ path = {:?}, silence_floor_ms = 0, flow_control = \"none\" }}\n",
        gw.display().to_string()
    );
    if learned {
        // A floor well above the machine's stalls: a spurious timeout would end the
        // run; every reply is still learned from.
        text += "[[line.unit]]\nunits = \"1-255\"\nresponse_timeout_ms = \"auto\"\n\
                 response_timeout_min_ms = 300\n";
    }
    let high = if classes { "priority = 1\n" } else { "" };
    text += &format!("[[listen]]\naddress = \"127.0.0.1:0\"\n{high}");
    text += "[[listen]]\naddress = \"127.0.0.1:0\"\n[log]\nlevel = \"info\"\n";
    text
}

/// Both listeners' addresses, from the log.
fn listeners(gw: &Gateway) -> Vec<SocketAddr> {
    let log = gw.log();
    log.split("listening on ")
        .skip(1)
        .filter_map(|rest| rest.split_whitespace().next()?.parse().ok())
        .collect()
}

pub(super) fn units_cost(r: &mut Report) {
    eprintln!("units: two masters polling, with and without learned timeouts and classes");
    const WARM: usize = 200;
    const N: usize = 4000;
    const ROUNDS: usize = 4;
    const CASES: [(&str, bool, bool); 3] = [
        ("the line's timeout, one class", false, false),
        ("every unit's timeout learned", true, false),
        ("the masters in classes 1 and 0", false, true),
    ];
    let line = Line::start(&[]);
    let mut lat = vec![Vec::new(); CASES.len()];
    let mut cpu = [0u64; CASES.len()];
    let mut transactions = [0usize; CASES.len()];
    for _ in 0..ROUNDS {
        for (i, (_, learned, classes)) in CASES.into_iter().enumerate() {
            let text = config(&line.socat.gw, learned, classes);
            eprintln!("  {}", CASES[i].0);
            let mut gw = Gateway::launch_text(&text, line.dir.path(), Launch::default());
            gw.wait_log("serial port open", Duration::from_secs(5));
            let addrs = listeners(&gw);
            assert_eq!(addrs.len(), 2, "two listeners");
            let pid = gw.proc.pid();
            let cpu0 = cpu_ns(pid);
            let masters: Vec<_> = addrs
                .into_iter()
                .map(|addr| {
                    thread::spawn(move || {
                        let mut s = TcpStream::connect(addr).unwrap();
                        s.set_nodelay(true).unwrap();
                        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
                        let mut out = Vec::new();
                        for tid in 0..(WARM + N / ROUNDS / 2) as u16 {
                            let took = tcp_read(&mut s, tid, 1);
                            if usize::from(tid) >= WARM {
                                out.push(took);
                            }
                        }
                        out
                    })
                })
                .collect();
            for m in masters {
                lat[i].extend(m.join().expect("a master"));
            }
            cpu[i] += cpu_ns(pid) - cpu0;
            transactions[i] += 2 * WARM + N / ROUNDS;
            gw.terminate(Duration::from_secs(5));
        }
    }
    let per = |i: usize| Duration::from_nanos(cpu[i]) / transactions[i] as u32;
    let mut t = String::from(
        "| case | CPU per transaction (process) | p50 | p99 | max |\n|---|---|---|---|---|\n",
    );
    for (i, (name, _, _)) in CASES.into_iter().enumerate() {
        let x = spread(&lat[i]);
        let _ = writeln!(t, "| {name} | {} | {} |", us(per(i)), x.cells());
    }
    for (i, (name, _, _)) in CASES.into_iter().enumerate().skip(1) {
        let (a, b) = (per(0), per(i));
        let pct = (b.as_secs_f64() / a.as_secs_f64() - 1.0) * 100.0;
        r.row(
            "units",
            &format!("{name}: CPU per transaction against the line's timeout, one class"),
            format!("{pct:+.1} % ({} → {})", us(a), us(b)),
            "< 5 %",
            Some(pct < 5.0),
        );
    }
    r.detail(
        &format!("Learned timeouts and priority classes ({N} transactions a case from two masters polling at once, in {ROUNDS} rounds taking turns, each after {WARM} warm-up a master; the simulator unpaced)"),
        &command("units"),
        &t,
    );
}
