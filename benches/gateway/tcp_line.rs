//! `tcp-line`: a device on the network: FC 03 to `mbgate sim --listen` directly,
//! through a bare socat byte pipe and through mbgate's TCP line.

use super::common::{socat_to, tempdir, Gateway, Launch};
use super::report::{command, diff_us, spread, us, Report};
use super::shared::{network_sim, samples, served, tcp_read};
use std::fmt::Write as _;
use std::time::Duration;

/// FC 03 to `mbgate sim --listen` (a Modbus/TCP device on the network) directly,
/// through a bare TCP byte pipe (socat), and through mbgate's TCP line: what the
/// gateway adds when the device is on the network.
pub(super) fn tcp_line(r: &mut Report) {
    eprintln!("tcp-line: FC 03 straight to a device on TCP, through socat, through mbgate");
    const WARM: usize = 200;
    const N: usize = 2000;
    const ROUNDS: usize = 4;
    let dir = tempdir();
    let (_sim, at) = network_sim();
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
        let _ = writeln!(t, "| {path} | {} |", x.cells());
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
