//! `rtu-limit`: RTU (and ASCII) at the line's limit, side by side with mbusd: one
//! master polling straight on the pty, through mbgate and through mbusd (ASCII: through
//! mbgate and a bare byte pipe), each path on a pty pair and simulator of its own.

use super::common::sim::RawLine;
use super::common::{cpu_ns, Cfg, Gateway};
use super::report::{diff_us, ms, pct, spread, us, Report};
use super::shared::{byte_pipe, serial_read, serial_reply_len, tcp_read, Line, MAX_TRANSACTIONS};
use super::timer_floor::timer_floor;
use std::fmt::Write as _;
use std::net::TcpStream;
use std::path::Path;
use std::thread;
use std::time::{Duration, Instant};

/// A gateway under test in the side-by-side RTU scenario: where masters connect, and
/// its process for the CPU it spends.
struct Contender {
    name: String,
    addr: std::net::SocketAddr,
    pid: u32,
    /// Keeps the line (pty pair and simulator) alive.
    _line: Line,
    _proc: ContenderProc,
}

enum ContenderProc {
    Mbgate(#[allow(dead_code)] Gateway),
    Mbusd(std::process::Child),
}

impl Drop for ContenderProc {
    fn drop(&mut self) {
        if let ContenderProc::Mbusd(c) = self {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// The line's limit with a fast device: pymodbus' own RTU server on a pty, unpaced (it
/// answers as fast as Python does), the line set to 115 200 baud. A pty has no wire:
/// nothing can collide there, so mbgate keeps no gap after a whole reply
/// (docs/reliability.md "Knowing the wire") and a request follows it at once. Direct,
/// through mbgate (the default, and `inter_frame_gap_us = 1000`, which is kept on a
/// pty too) and through mbusd `-R 1`, each on a pty pair and server of its own, in
/// turns. The targets: mbgate's p50 at most 150 µs above the direct p50, and at least
/// mbusd's transactions a second.
fn rtu_unpaced(r: &mut Report, round: Duration, rounds: usize, mbusd: Option<&Path>) -> String {
    const BAUD: u32 = 115_200;
    let t35 = Duration::from_micros(mbgate::frame::rtu::t35_us(BAUD, 10));
    eprintln!("rtu-limit: pymodbus RTU server, unpaced, FC 03 × 1");
    let mut paths = vec![
        mbgate_contender_on(Line::pymodbus_rtu(BAUD), "rtu", "mbgate", BAUD, &[]),
        mbgate_contender_on(
            Line::pymodbus_rtu(BAUD),
            "rtu",
            "mbgate, gap 1000 µs",
            BAUD,
            &["inter_frame_gap_us = 1000"],
        ),
    ];
    if let Some(m) = mbusd {
        paths.push(mbusd_contender_on(Line::pymodbus_rtu(BAUD), m, BAUD));
    }
    let direct_line = Line::pymodbus_rtu(BAUD);
    let LimitRows {
        direct,
        direct_gap,
        via,
    } = LimitRows::measure(&direct_line, &paths, 1, t35, round, rounds);
    let d = spread(&direct.times).p50;
    let cell = |p: &LimitRow| format!("{:.1} ({})", p.rate(), ms(spread(&p.times).p50));
    let above = |p: &LimitRow| spread(&p.times).p50.saturating_sub(d);
    let g = &via[0];
    let bound = Duration::from_micros(150);
    let (busd, ratio) = match paths.iter().position(|p| p.name.starts_with("mbusd")) {
        Some(i) => {
            let ratio = g.rate() / via[i].rate();
            r.row(
                "rtu-limit",
                "RTU on a pty, pymodbus server unpaced: mbgate / mbusd -R 1 (tx/s)",
                format!("{ratio:.2}"),
                "≥ 1.0",
                Some(ratio >= 1.0),
            );
            (
                format!("{} (+{})", cell(&via[i]), us(above(&via[i]))),
                format!("**{ratio:.2}**"),
            )
        }
        None => ("(MBUSD not set)".into(), "-".into()),
    };
    r.row(
        "rtu-limit",
        "RTU on a pty, pymodbus server unpaced: mbgate's p50 above direct",
        format!("{} (no gap on a pty; t3.5 = {})", us(above(g)), us(t35)),
        "≤ 150 µs",
        Some(above(g) <= bound),
    );
    format!(
        "A fast device: pymodbus' own RTU server (`tests/py/stock_server.py --framer rtu`) on a pty (no wire: no gap after a whole reply), unpaced, the line set to {BAUD} baud (t3.5 = {}); tx/s (p50), and in brackets after it the p50 above direct:\n\n\
         | direct tx/s (p50) | mbgate tx/s (p50) | mbgate above direct, p50 | target | direct keeping t3.5 (p50 above direct) | mbgate CPU/tx | mbgate gap 1000 µs | mbusd -R 1 | mbgate / mbusd |\n|---|---|---|---|---|---|---|---|---|\n\
         | {} | {} | **{}** | ≤ {} | {} (+{}) | {} | {} (+{}) | {busd} | {ratio} |\n",
        us(t35),
        cell(&direct),
        cell(g),
        us(above(g)),
        us(bound),
        cell(&direct_gap),
        us(above(&direct_gap)),
        g.cpu_per_tx(),
        cell(&via[1]),
        us(above(&via[1])),
    )
}

/// The simulator as an RTU device paced at `baud` on a pty pair of its own.
fn rtu_sim_line(baud: u32) -> Line {
    serial_sim_line("rtu", baud)
}

/// The simulator as a paced device in `framing` at `baud` on a pty pair of its own.
fn serial_sim_line(framing: &str, baud: u32) -> Line {
    let speed = baud.to_string();
    Line::start_probed(
        &["--framing", framing, "--baud", &speed],
        &serial_read(framing, 1),
        serial_reply_len(framing, 1),
    )
}

/// `mbgate run` in RTU at `baud`, no flow control, with extra `[serial]` lines.
fn mbgate_contender(name: &str, baud: u32, serial: &[&str]) -> Contender {
    mbgate_contender_in("rtu", name, baud, serial)
}

/// [`mbgate_contender`] in `framing`. The simulator paces its bytes as a wire at
/// `baud` would, so the port is declared one (`port_kind = "wire"`): the gap and the
/// line's limit are a wire's.
fn mbgate_contender_in(framing: &str, name: &str, baud: u32, serial: &[&str]) -> Contender {
    let serial: Vec<&str> = std::iter::once("port_kind = \"wire\"")
        .chain(serial.iter().copied())
        .collect();
    mbgate_contender_on(serial_sim_line(framing, baud), framing, name, baud, &serial)
}

/// [`mbgate_contender_in`] in front of the device on `line`.
fn mbgate_contender_on(
    line: Line,
    framing: &str,
    name: &str,
    baud: u32,
    serial: &[&str],
) -> Contender {
    let mut cfg = Cfg::new(&line.socat.gw)
        .serial(&format!("framing = {framing:?}"))
        .serial("flow_control = \"none\"")
        .serial(&format!("baud_rate = {baud}"));
    for l in serial {
        cfg = cfg.serial(l);
    }
    let gw = line.gateway_with(cfg, &[], &[]);
    Contender {
        name: name.into(),
        addr: gw.addr,
        pid: gw.proc.pid(),
        _line: line,
        _proc: ContenderProc::Mbgate(gw),
    }
}

/// mbusd (`MBUSD=/path/to/mbusd`) in front of the same simulator at `baud`, with its
/// pause between requests at its least (`-R 1`, 1 ms), no retries.
fn mbusd_contender(mbusd: &Path, baud: u32) -> Contender {
    mbusd_contender_on(rtu_sim_line(baud), mbusd, baud)
}

/// [`mbusd_contender`] in front of the device on `line`.
fn mbusd_contender_on(line: Line, mbusd: &Path, baud: u32) -> Contender {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port();
    let child = std::process::Command::new(mbusd)
        .args(["-d", "-L", "-", "-v", "0", "-p"])
        .arg(&line.socat.gw)
        .args(["-s", &baud.to_string(), "-m", "8N1", "-A", "127.0.0.1"])
        .args([
            "-P",
            &port.to_string(),
            "-R",
            "1",
            "-W",
            "500",
            "-N",
            "0",
            "-T",
            "0",
        ])
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("start mbusd");
    let addr = std::net::SocketAddr::from(([127, 0, 0, 1], port));
    let start = Instant::now();
    while TcpStream::connect(addr).is_err() {
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "mbusd never listened"
        );
        thread::sleep(Duration::from_millis(20));
    }
    Contender {
        name: "mbusd -R 1".into(),
        addr,
        pid: child.id(),
        _line: line,
        _proc: ContenderProc::Mbusd(child),
    }
}

/// One master polling FC 03 × `qty` for `budget`: each transaction's time.
fn poll_for(budget: Duration, mut f: impl FnMut(u16) -> Duration) -> Vec<Duration> {
    for tid in 0..8 {
        f(tid);
    }
    let start = Instant::now();
    let mut v = Vec::new();
    while start.elapsed() < budget && v.len() < MAX_TRANSACTIONS {
        v.push(f(v.len() as u16));
    }
    v
}

/// One master straight on the device's pty, polling with `req` (answered in `len`
/// bytes) for `round`, sleeping `gap` before each request (zero: none); each
/// transaction's time, the sleep included.
fn poll_direct(
    m: &mut RawLine,
    req: &[u8],
    len: usize,
    round: Duration,
    gap: Duration,
) -> Vec<Duration> {
    poll_for(round, |_| {
        let t = Instant::now();
        if !gap.is_zero() {
            thread::sleep(gap);
        }
        assert_eq!(m.transact(req, len).len(), len, "short reply");
        t.elapsed()
    })
}

/// One master polling FC 03 × `qty` through `p` for `round`: its transaction times and
/// the CPU `p` spent on them go into `out`.
fn poll_through(p: &Contender, qty: u16, round: Duration, out: &mut LimitRow) {
    let mut s = TcpStream::connect(p.addr).expect("connect");
    s.set_nodelay(true).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let cpu0 = cpu_ns(p.pid);
    let times = poll_for(round, |tid| tcp_read(&mut s, tid, qty));
    out.cpu_ns += cpu_ns(p.pid) - cpu0;
    out.times.extend(times);
}

/// The paths of one RTU row of the line's limit.
struct LimitRows {
    /// A master straight on the device's pty.
    direct: LimitRow,
    /// The same master keeping the gap itself after each reply, on a sleep as precise
    /// as the gateway's timer: what a transaction takes on this machine when the line
    /// is left silent for the gap, whoever keeps it.
    direct_gap: LimitRow,
    /// A master through each of the paths, in their order.
    via: Vec<LimitRow>,
}

impl LimitRows {
    /// FC 03 × `qty` polled on each path in turn for `round`, `rounds` times: straight
    /// on `device`'s pty, the same keeping `gap`, then through each of `paths`.
    fn measure(
        device: &Line,
        paths: &[Contender],
        qty: u16,
        gap: Duration,
        round: Duration,
        rounds: usize,
    ) -> LimitRows {
        let (req, len) = (serial_read("rtu", qty), serial_reply_len("rtu", qty));
        let mut rows = LimitRows {
            direct: LimitRow::default(),
            direct_gap: LimitRow::default(),
            via: vec![LimitRow::default(); paths.len()],
        };
        for _ in 0..rounds {
            let mut m = device.raw();
            let direct = poll_direct(&mut m, &req, len, round, Duration::ZERO);
            rows.direct.times.extend(direct);
            let kept = poll_direct(&mut m, &req, len, round, gap);
            rows.direct_gap.times.extend(kept);
            drop(m);
            for (p, out) in paths.iter().zip(rows.via.iter_mut()) {
                poll_through(p, qty, round, out);
            }
        }
        rows
    }
}

/// Per path of one row: transaction times, and CPU nanoseconds spent on them.
#[derive(Default, Clone)]
struct LimitRow {
    times: Vec<Duration>,
    cpu_ns: u64,
}

impl LimitRow {
    fn rate(&self) -> f64 {
        self.times.len() as f64 / self.times.iter().sum::<Duration>().as_secs_f64()
    }

    /// The CPU its process spent a transaction, as a cell. The warm-up transactions
    /// are not in `times`: slightly high.
    fn cpu_per_tx(&self) -> String {
        us(Duration::from_nanos(
            self.cpu_ns / self.times.len().max(1) as u64,
        ))
    }
}

/// The line's own limit, side by side: the simulator as a paced RTU device at 9600 to
/// 921 600 baud, one master polling FC 03 × 1 and × 10 as fast as answered, straight on
/// the pty (the device's pace and turnaround), through mbgate (the default gap, t3.5
/// of Modbus over Serial Line V1.02 §2.5.1.1, and above 19 200 baud also with
/// `inter_frame_gap_us = 1000`) and, given `MBUSD=/path/to/mbusd`, through mbusd
/// `-R 1`; each path on a pty pair and simulator of its own, the paths taking turns
/// (A B A B) for `MBGATE_BENCH_RTU_ROUND_MS` (default 1000) each
/// (`MBGATE_BENCH_RTU_BAUDS` picks speeds). The limit: the
/// direct transaction time plus exactly the gap.
pub(super) fn rtu_limit(r: &mut Report) {
    const ROUNDS: usize = 2;
    // The master's own sleeps as precise as a timerfd: no 50 µs of timer slack.
    // SAFETY: PR_SET_TIMERSLACK takes a number and changes only this thread's slack.
    #[allow(unsafe_code)]
    unsafe {
        libc::prctl(libc::PR_SET_TIMERSLACK, 1 as libc::c_ulong);
    }
    let round = Duration::from_millis(
        std::env::var("MBGATE_BENCH_RTU_ROUND_MS")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(1000),
    );
    let mbusd = std::env::var_os("MBUSD").map(std::path::PathBuf::from);
    if mbusd.is_none() {
        eprintln!("rtu-limit: MBUSD not set: the mbusd column is skipped (MBUSD=/path/to/mbusd)");
    }
    let mut t = String::from(
        "| baud | registers | direct tx/s (p50) | limit with t3.5 | mbgate tx/s (p50) | mbgate / limit | mbgate p50 − direct p50 − t3.5 | direct keeping t3.5 tx/s (p50) | mbgate / it | mbgate CPU/tx | mbgate gap 1000 µs tx/s (p50) | mbusd -R 1 tx/s (p50) | mbgate / mbusd | mbusd CPU/tx |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    // `MBGATE_BENCH_RTU_BAUDS=115200,921600` measures only those speeds.
    let bauds: Vec<u32> = std::env::var("MBGATE_BENCH_RTU_BAUDS")
        .ok()
        .map(|v| v.split(',').filter_map(|b| b.trim().parse().ok()).collect())
        .unwrap_or_else(|| vec![9600, 19_200, 115_200, 921_600]);
    for baud in bauds {
        let t35 = Duration::from_micros(mbgate::frame::rtu::t35_us(baud, 10));
        let mut paths = vec![mbgate_contender("mbgate", baud, &[])];
        if baud > 19_200 {
            paths.push(mbgate_contender(
                "mbgate, gap 1000 µs",
                baud,
                &["inter_frame_gap_us = 1000"],
            ));
        }
        if let Some(m) = &mbusd {
            paths.push(mbusd_contender(m, baud));
        }
        let direct_line = rtu_sim_line(baud);
        for qty in [1u16, 10] {
            eprintln!("rtu-limit: {baud} baud, FC 03 × {qty}");
            let LimitRows {
                direct,
                direct_gap,
                via,
            } = LimitRows::measure(&direct_line, &paths, qty, t35, round, ROUNDS);
            let d = spread(&direct.times);
            let per_direct = 1.0 / direct.rate();
            let limit = 1.0 / (per_direct + t35.as_secs_f64());
            let cell = |p: &LimitRow| format!("{:.1} ({})", p.rate(), ms(spread(&p.times).p50));
            let g = &via[0];
            let gap = paths
                .iter()
                .position(|p| p.name.contains("gap"))
                .map_or("-".into(), |i| cell(&via[i]));
            let busd = paths.iter().position(|p| p.name.starts_with("mbusd"));
            let (busd_cell, ratio, busd_cpu) = match busd {
                Some(i) => (
                    cell(&via[i]),
                    format!("**{:.2}**", g.rate() / via[i].rate()),
                    via[i].cpu_per_tx(),
                ),
                None => ("(MBUSD not set)".into(), "-".into(), "-".into()),
            };
            let _ = writeln!(
                t,
                "| {baud} | {qty} | {:.1} ({}) | {limit:.1}/s | {} | **{}** | {:+.1} µs | {} | {} | {} | {gap} | {busd_cell} | {ratio} | {busd_cpu} |",
                direct.rate(),
                ms(d.p50),
                cell(g),
                pct(g.rate() / limit),
                diff_us(d.p50 + t35, spread(&g.times).p50),
                cell(&direct_gap),
                pct(g.rate() / direct_gap.rate()),
                g.cpu_per_tx(),
            );
            r.row(
                "rtu-limit",
                &format!("RTU {baud} baud FC 03 × {qty}: mbgate against the line's limit (direct + t3.5)"),
                format!("{:.1}/s of {limit:.1}/s = {}", g.rate(), pct(g.rate() / limit)),
                "≥ 98 %",
                Some(g.rate() >= 0.98 * limit),
            );
        }
    }
    let unpaced = rtu_unpaced(r, round, ROUNDS, mbusd.as_deref());
    let _ = write!(t, "\n{unpaced}");
    // ASCII: its limit is the wire time alone (no gap between frames).
    let mut a = String::from(
        "| baud | registers | direct tx/s (p50) | mbgate tx/s (p50) | mbgate / direct | mbgate CPU/tx | byte pipe tx/s (p50) | byte pipe / direct | mbgate / byte pipe | byte pipe CPU/tx |\n|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for baud in [9600u32, 115_200] {
        let gw = mbgate_contender_in("ascii", "mbgate ascii", baud, &[]);
        let direct_line = serial_sim_line("ascii", baud);
        let qty = 1;
        eprintln!("rtu-limit: ASCII {baud} baud, FC 03 × {qty}");
        let req = serial_read("ascii", qty);
        let len = serial_reply_len("ascii", qty);
        // Any path over TCP costs the master a hop that a master on the pty does not
        // make: a bare byte pipe (socat, TCP to the pty) carrying the same ASCII
        // frames is what such a path reaches on this machine.
        let pipe_line = serial_sim_line("ascii", baud);
        let (mut pipe, mut ps) = byte_pipe(&pipe_line);
        let (mut direct, mut via, mut piped) = (
            LimitRow::default(),
            LimitRow::default(),
            LimitRow::default(),
        );
        for _ in 0..ROUNDS {
            let mut m = direct_line.raw();
            direct
                .times
                .extend(poll_direct(&mut m, &req, len, round, Duration::ZERO));
            drop(m);
            poll_through(&gw, qty, round, &mut via);
            let cpu0 = cpu_ns(pipe.id());
            piped.times.extend(poll_for(round, |_| {
                use std::io::{Read as _, Write as _};
                let t = Instant::now();
                ps.write_all(&req).expect("send to socat");
                let mut reply = vec![0; len];
                ps.read_exact(&mut reply).expect("the reply through socat");
                t.elapsed()
            }));
            piped.cpu_ns += cpu_ns(pipe.id()) - cpu0;
        }
        drop(ps);
        let _ = pipe.kill();
        let _ = pipe.wait();
        let ratio = via.rate() / direct.rate();
        let _ = writeln!(
            a,
            "| {baud} | {qty} | {:.1} ({}) | {:.1} ({}) | **{}** | {} | {:.1} ({}) | {} | **{}** | {} |",
            direct.rate(),
            ms(spread(&direct.times).p50),
            via.rate(),
            ms(spread(&via.times).p50),
            pct(ratio),
            via.cpu_per_tx(),
            piped.rate(),
            ms(spread(&piped.times).p50),
            pct(piped.rate() / direct.rate()),
            pct(via.rate() / piped.rate()),
            piped.cpu_per_tx(),
        );
        r.row(
            "rtu-limit",
            &format!("ASCII {baud} baud FC 03 × {qty}: mbgate against the line's limit (direct)"),
            format!(
                "{:.1}/s of {:.1}/s = {}",
                via.rate(),
                direct.rate(),
                pct(ratio)
            ),
            "≥ 98 %",
            Some(ratio >= 0.98),
        );
    }
    let _ = write!(t, "\nASCII (the same, `--framing ascii`; no gap between frames, so the limit is the direct rate):\n\n{a}");
    let note = if mbusd.is_some() {
        ""
    } else {
        "\nmbusd not measured: run with `MBUSD=/path/to/mbusd` (built from github.com/3cky/mbusd with cmake).\n"
    };
    let floor = timer_floor();
    let _ = write!(
        t,
        "\nThis machine's timer floor (a timerfd set 1750 µs ahead, 1000 times, on an idle runtime): late by {} at p50, {} at p99. The gap costs a gateway one such wake more than a master talking straight to the device.\n",
        us(floor.p50),
        us(floor.p99),
    );
    r.detail(
        &format!("RTU at the line's limit (the simulator paced as a UART, 10 bits a byte; one master polling; each path on its own pty pair and simulator; paths in turn, {ROUNDS} rounds of {round:?} each; p50 of the transaction time in brackets)"),
        "MBUSD=/path/to/mbusd cargo bench --bench gateway -- rtu-limit",
        &format!("{t}{note}"),
    );
}
