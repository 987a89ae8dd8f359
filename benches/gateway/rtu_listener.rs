//! `rtu-listener`: FC 03 from an RTU-over-TCP master and from a Modbus/TCP master
//! through one gateway: what the RTU framing on the masters' side costs.

use super::common::{Gateway, Launch};
use super::report::{command, diff_us, spread, us, Report};
use super::shared::{connect, rtu_reply_len, samples, tcp_read, Line};
use std::fmt::Write as _;
use std::io::Write as _;
use std::net::TcpStream;
use std::thread;
use std::time::{Duration, Instant};

/// FC 03 from an RTU-over-TCP master and from a Modbus/TCP master, taking turns,
/// through one gateway with both listeners to the simulator (RTU) on a pty: what the
/// RTU framing on the masters' side costs.
pub(super) fn rtu_listener(r: &mut Report) {
    eprintln!("rtu-listener: FC 03 through an rtu listener and an mbap one");
    const WARM: usize = 200;
    const N: usize = 2000;
    const ROUNDS: usize = 4;
    // An RTU line at the fastest speed there is, to an unpaced simulator: a reply is
    // taken the moment its last byte arrives, so the line adds the least it can.
    let probe = mbgate::frame::rtu::encode(1, &[0x03, 0, 0, 0, 1]);
    let line = Line::start_probed(&["--framing", "rtu"], &probe, rtu_reply_len(1));
    let text = format!(
        "[[line]]\n[line.serial]\npath = {:?}\nframing = \"rtu\"\nflow_control = \"none\"\n\
         baud_rate = 4000000\nsilence_floor_ms = 0\n\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\n\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\nframing = \"rtu\"\n\n[log]\nlevel = \"info\"\n",
        line.socat.gw.display().to_string()
    );
    let mut gw = Gateway::launch_text(&text, line.dir.path(), Launch::default());
    let rtu_at = {
        let start = Instant::now();
        loop {
            let log = gw.proc.log();
            if let Some(a) = log.split("listening on ").nth(2) {
                break a.split_whitespace().next().unwrap().to_string();
            }
            assert!(start.elapsed() < Duration::from_secs(10), "no rtu listener");
            thread::sleep(Duration::from_millis(10));
        }
    };
    let mut m = connect(&gw);
    let mut rtu = TcpStream::connect(&rtu_at).unwrap();
    rtu.set_nodelay(true).unwrap();
    rtu.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let request = mbgate::frame::rtu::encode(1, &[0x03, 0, 0, 0, 1]);
    let mut rtu_read = |_tid: u16| {
        let t = Instant::now();
        rtu.write_all(&request).unwrap();
        let mut reply = vec![0u8; rtu_reply_len(1)];
        std::io::Read::read_exact(&mut rtu, &mut reply).unwrap();
        let took = t.elapsed();
        assert_eq!(reply[1], 0x03, "not a normal reply: {reply:02X?}");
        took
    };
    let (mut mbap, mut rtu_samples) = (vec![], vec![]);
    for _ in 0..ROUNDS {
        mbap.extend(samples(WARM, N / ROUNDS, |tid| tcp_read(&mut m, tid, 1)));
        rtu_samples.extend(samples(WARM, N / ROUNDS, &mut rtu_read));
    }
    gw.terminate(Duration::from_secs(5));
    let (a, b) = (spread(&mbap), spread(&rtu_samples));
    let mut t = String::from("| master | p50 | p99 | max |\n|---|---|---|---|\n");
    for (who, x) in [
        ("Modbus/TCP (mbap listener)", a),
        ("RTU over TCP (rtu listener)", b),
    ] {
        let _ = writeln!(t, "| {who} | {} |", x.cells());
    }
    let more = diff_us(a.p50, b.p50);
    r.row(
        "rtu-listener",
        "RTU-over-TCP master against a Modbus/TCP one, p50, FC 03 × 1",
        format!("{more:+.0} µs ({} → {})", us(a.p50), us(b.p50)),
        "≤ 50 µs",
        Some(more <= 50.0),
    );
    r.detail(
        &format!("RTU over TCP masters ({N} samples each, in {ROUNDS} rounds taking turns, each after {WARM} warm-up; the simulator on a pty as an RTU device, unpaced, the line at 4 000 000 baud)"),
        &command("rtu-listener"),
        &t,
    );
}
