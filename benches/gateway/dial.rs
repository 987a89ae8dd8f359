//! `dial`: FC 03 from three masters through one gateway, taking turns: one that
//! connected to it (a `[[listen]]`), one it dialed (a `[[dial]]` to a listener in this
//! process) and one over UDP (`transport = "udp"`): what the dialed and the datagram
//! sources of the one connection type cost against an accepted connection.

use super::common::{cpu_ns, read_req, Gateway, Launch};
use super::report::{command, diff_us, spread, us, Report};
use super::shared::{connect, reply_len, rtu_reply_len, samples, tcp_read, Line};
use std::fmt::Write as _;
use std::net::{TcpListener, UdpSocket};
use std::thread;
use std::time::{Duration, Instant};

/// One FC 03 round trip over UDP; panics unless it is the normal reply.
fn udp_read(s: &UdpSocket, tid: u16) -> Duration {
    let req = read_req(tid, 1, 0, 1);
    let t = Instant::now();
    s.send(&req).expect("send");
    let mut buf = [0u8; 300];
    let n = s.recv(&mut buf).expect("a reply within 5 s");
    let took = t.elapsed();
    assert_eq!(
        (n, buf[7], &buf[..2]),
        (reply_len(1), 0x03, &req[..2]),
        "{:02X?}",
        &buf[..n]
    );
    took
}

pub(super) fn dial(r: &mut Report) {
    eprintln!("dial: FC 03 from an accepted, a dialed and a UDP master");
    const WARM: usize = 200;
    const N: usize = 2000;
    const ROUNDS: usize = 4;
    let probe = mbgate::frame::rtu::encode(1, &[0x03, 0, 0, 0, 1]);
    let line = Line::start_probed(&["--framing", "rtu"], &probe, rtu_reply_len(1));
    let server = TcpListener::bind("127.0.0.1:0").unwrap();
    let text = format!(
        "[[line]]\n[line.serial]\npath = {:?}\nframing = \"rtu\"\nflow_control = \"none\"\n\
         baud_rate = 4000000\nsilence_floor_ms = 0\n\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\n\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\ntransport = \"udp\"\n\n\
         [[dial]]\naddress = \"{}\"\nbackoff_min_ms = 100\n\n[log]\nlevel = \"info\"\n",
        line.socat.gw.display().to_string(),
        server.local_addr().unwrap()
    );
    let mut gw = Gateway::launch_text(&text, line.dir.path(), Launch::default());
    let udp_at = {
        let start = Instant::now();
        loop {
            let log = gw.proc.log();
            if let Some(a) = log.split("listening on ").nth(2) {
                break a.split_whitespace().next().unwrap().to_string();
            }
            assert!(start.elapsed() < Duration::from_secs(10), "no udp listener");
            thread::sleep(Duration::from_millis(10));
        }
    };
    let (mut dialed, _) = server.accept().unwrap();
    dialed.set_nodelay(true).unwrap();
    dialed
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    let mut m = connect(&gw);
    let udp = UdpSocket::bind("127.0.0.1:0").unwrap();
    udp.connect(&udp_at).unwrap();
    udp.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let pid = gw.proc.pid();
    let mut cpu = [0u64; 3];
    let mut all: [Vec<Duration>; 3] = Default::default();
    for _ in 0..ROUNDS {
        let mut timed = |k: usize, f: &mut dyn FnMut(u16) -> Duration| {
            for i in 0..WARM {
                f(i as u16);
            }
            let c0 = cpu_ns(pid);
            all[k].extend(samples(0, N / ROUNDS, &mut *f));
            cpu[k] += cpu_ns(pid) - c0;
        };
        timed(0, &mut |tid| tcp_read(&mut m, tid, 1));
        timed(1, &mut |tid| tcp_read(&mut dialed, tid, 1));
        timed(2, &mut |tid| udp_read(&udp, tid));
    }
    gw.terminate(Duration::from_secs(5));
    let s: Vec<_> = all.iter().map(|x| spread(x)).collect();
    let per = |k: usize| cpu[k] as f64 / N as f64 / 1000.0;
    let mut t = String::from(
        "| master | p50 | p99 | max | gateway CPU a transaction |\n|---|---|---|---|---|\n",
    );
    for (k, who) in [
        "accepted (a [[listen]])",
        "dialed (a [[dial]])",
        "UDP (transport = \"udp\")",
    ]
    .iter()
    .enumerate()
    {
        let _ = writeln!(t, "| {who} | {} | {:.1} µs |", s[k].cells(), per(k));
    }
    let within = |a: Duration, b: Duration| diff_us(a, b) <= a.as_secs_f64() * 1e6 * 0.05;
    for (k, measure) in [
        (1, "dialed master against an accepted one, p50, FC 03 × 1"),
        (2, "UDP master against a TCP one, p50, FC 03 × 1"),
    ] {
        r.row(
            "dial",
            measure,
            format!(
                "{:+.0} µs ({} → {}); CPU {:.1} → {:.1} µs a transaction",
                diff_us(s[0].p50, s[k].p50),
                us(s[0].p50),
                us(s[k].p50),
                per(0),
                per(k)
            ),
            "within 5 %",
            Some(within(s[0].p50, s[k].p50)),
        );
    }
    r.detail(
        &format!("Dialed and UDP masters ({N} samples each, in {ROUNDS} rounds taking turns, each after {WARM} warm-up; the simulator on a pty as an RTU device, unpaced, the line at 4 000 000 baud; CPU: the gateway's, from /proc schedstat over the samples)"),
        &command("dial"),
        &t,
    );
}
