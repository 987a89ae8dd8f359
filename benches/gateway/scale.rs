//! `scale`: how a transaction's cost grows with lines and masters. 1, 4 and 8 lines
//! (each a pty pair with the simulator answering at once, its own unit) behind one
//! gateway, and 1, 10 and 100 masters spread over them, each polling FC 03 × 1 of its
//! line's unit: transactions a second summed, the gateway's CPU per transaction, its
//! peak RSS, and the p99 round trip. The cost per transaction must stay flat as lines
//! and masters grow: no work per transaction that counts the masters or the lines
//! (docs/performance.md "How cost grows"). With `MBGATE_BENCH_BASELINE=PATH` (another
//! mbgate build, e.g. the commit before a change) each cell is measured with it too,
//! the two builds in turns on the same lines.

use super::common::{cpu_ns, read_req, Gateway, Launch};
use super::report::{command, ms, spread, us, Report};
use super::shared::{proc_status, reply_len, Line, MAX_TRANSACTIONS};
use std::fmt::Write as _;
use std::io::Write as _;
use std::net::TcpStream;
use std::sync::{Arc, Barrier};
use std::thread;
use std::time::{Duration, Instant};

/// What one cell of the table measured.
struct Cell {
    rate: f64,
    cpu_per: Duration,
    hwm_kib: u64,
    p99: Duration,
}

/// The gateway in front of `lines`: line `i` serves unit `i + 1`, unpaced MBAP on its
/// pty, every request its own transaction (the masters poll the same reads, which
/// coalescing would merge), room for 100 masters.
fn gateway(lines: &[Line], dir: &std::path::Path, program: Option<&std::ffi::OsStr>) -> Gateway {
    let mut text = String::from("[log]\nlevel = \"info\"\n\n");
    for (i, line) in lines.iter().enumerate() {
        let _ = write!(
            text,
            "[[line]]\nunits = [{}]\n[line.serial]\npath = {:?}\nframing = \"mbap\"\nsilence_floor_ms = 0\n[line.relay]\nqueue_depth = 256\ncoalesce = false\n\n",
            i + 1,
            line.socat.gw.display().to_string(),
        );
    }
    text += "[[listen]]\naddress = \"127.0.0.1:0\"\nmax_connections = 256\n";
    let launch = match program {
        Some(p) => Launch::default().program(p),
        None => Launch::default(),
    };
    Gateway::launch_text(&text, dir, launch)
}

/// `masters` masters, master `j` on unit `j % lines + 1`, poll together for `window`
/// after `warm`; the gateway's CPU is read across the window.
fn measure(gw: &Gateway, lines: usize, masters: usize, warm: Duration, window: Duration) -> Cell {
    let barrier = Arc::new(Barrier::new(masters + 1));
    let pid = gw.proc.pid();
    let handles: Vec<_> = (0..masters)
        .map(|j| {
            let barrier = barrier.clone();
            let mut s = TcpStream::connect(gw.addr).expect("connect");
            s.set_nodelay(true).unwrap();
            s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
            let unit = (j % lines + 1) as u8;
            thread::spawn(move || {
                barrier.wait();
                let t0 = Instant::now();
                let (open, close) = (t0 + warm, t0 + warm + window);
                let mut took = Vec::new();
                let mut reply = vec![0u8; reply_len(1)];
                for tid in 0..MAX_TRANSACTIONS {
                    let sent = Instant::now();
                    if sent >= close {
                        break;
                    }
                    s.write_all(&read_req(tid as u16, unit, 0, 1))
                        .expect("send");
                    std::io::Read::read_exact(&mut s, &mut reply).expect("a reply");
                    assert_eq!(
                        (reply[..2] == (tid as u16).to_be_bytes(), reply[6], reply[7]),
                        (true, unit, 0x03),
                        "not this master's reply: {reply:02X?}"
                    );
                    let done = Instant::now();
                    if sent >= open && done <= close {
                        took.push(done - sent);
                    }
                }
                took
            })
        })
        .collect();
    barrier.wait();
    thread::sleep(warm);
    let cpu0 = cpu_ns(pid);
    thread::sleep(window);
    let cpu = cpu_ns(pid) - cpu0;
    let all: Vec<Duration> = handles
        .into_iter()
        .flat_map(|h| h.join().unwrap())
        .collect();
    let n = all.len().max(1);
    Cell {
        rate: all.len() as f64 / window.as_secs_f64(),
        cpu_per: Duration::from_nanos(cpu / n as u64),
        hwm_kib: proc_status(pid, "VmHWM"),
        p99: spread(&all).p99,
    }
}

pub(super) fn scale(r: &mut Report) {
    eprintln!("scale: 1, 4 and 8 lines × 1, 10 and 100 masters");
    let (warm, window) = (Duration::from_millis(300), Duration::from_secs(2));
    let baseline = std::env::var_os("MBGATE_BENCH_BASELINE");
    let mut builds: Vec<(String, Option<&std::ffi::OsStr>)> = vec![("this build".into(), None)];
    if let Some(b) = baseline.as_deref() {
        builds.push((
            format!("baseline `{}`", std::path::Path::new(b).display()),
            Some(b),
        ));
    }
    let mut t = String::from(
        "| lines | masters | build | transactions/s (sum) | CPU per transaction | peak RSS | p99 |\n|---|---|---|---|---|---|---|\n",
    );
    let (mut first, mut last) = (None, None);
    for n_lines in [1usize, 4, 8] {
        let lines: Vec<Line> = (0..n_lines)
            .map(|i| {
                let unit = (i + 1).to_string();
                Line::start_probed(
                    &["--units", &unit],
                    &read_req(1, (i + 1) as u8, 0, 1),
                    reply_len(1),
                )
            })
            .collect();
        for masters in [1usize, 10, 100] {
            for (k, (name, program)) in builds.iter().enumerate() {
                let mut gw = gateway(&lines, lines[0].dir.path(), *program);
                let c = measure(&gw, n_lines, masters, warm, window);
                gw.terminate(Duration::from_secs(5));
                let _ = writeln!(
                    t,
                    "| {n_lines} | {masters} | {name} | {:.0} | {} | {:.1} MiB | {} |",
                    c.rate,
                    us(c.cpu_per),
                    c.hwm_kib as f64 / 1024.0,
                    ms(c.p99),
                );
                if k == 0 {
                    first.get_or_insert(c.cpu_per);
                    last = Some(c.cpu_per);
                }
            }
        }
    }
    if let (Some(a), Some(b)) = (first, last) {
        let ratio = b.as_secs_f64() / a.as_secs_f64();
        r.row(
            "scale",
            "CPU per transaction, 8 lines × 100 masters against 1 × 1",
            format!("{ratio:.2} ({} → {})", us(a), us(b)),
            "≤ 1.25 (flat)",
            Some(ratio <= 1.25),
        );
    }
    r.detail(
        &format!("How cost grows (each cell {:.1} s after {} ms of warm-up, a gateway started for it; the simulator unpaced on each line's pty, MBAP, every request its own transaction)", window.as_secs_f64(), warm.as_millis()),
        &command("scale"),
        &t,
    );
}
