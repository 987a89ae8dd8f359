//! What the scenarios share: the peers (a pty pair with the simulator on its far end,
//! a gateway in front), one FC 03 round trip, the load loops, and a process's figures
//! from /proc.

use super::common::sim::RawLine;
use super::common::{read_frame, read_req, socat_pipe, tempdir, Cfg, Gateway, Proc, Py, Socat};
use super::report::Report;
use std::io::Write as _;
use std::net::TcpStream;
use std::thread;
use std::time::{Duration, Instant};

// ---------------------------------------------------------------------------------
// The peers and one round trip

/// Request bytes of an FC 03 read (MBAP): header 7 + function, address, quantity.
pub(super) const REQ: usize = 12;

/// Reply bytes of an FC 03 read of `qty` registers (MBAP).
pub(super) fn reply_len(qty: u16) -> usize {
    9 + 2 * usize::from(qty)
}

/// Upper bound on transactions in any one load loop, whatever its time budget.
pub(super) const MAX_TRANSACTIONS: usize = 200_000;

/// A pty pair and a quiet simulator on its device end: no per-packet log, started
/// once it answers a read from the gateway's end.
pub(super) struct Line {
    pub(super) dir: tempfile::TempDir,
    pub(super) socat: Socat,
    _sim: Device,
}

/// The device on a line's far end; stopped when the line drops.
enum Device {
    Sim(#[allow(dead_code)] Proc),
    Pymodbus(#[allow(dead_code)] Py),
}

impl Line {
    pub(super) fn start(sim_args: &[&str]) -> Line {
        Line::start_probed(sim_args, &read_req(1, 1, 0, 1), reply_len(1))
    }

    /// [`Line::start`], the simulator probed with `probe`, answered in `answer` bytes.
    pub(super) fn start_probed(sim_args: &[&str], probe_req: &[u8], answer: usize) -> Line {
        Line::probed(
            |dev| {
                let mut args = vec!["sim", "--serial", dev];
                args.extend(["--profile", "generic", "--log-level", "warn"]);
                args.extend_from_slice(sim_args);
                // No log line to wait for ("" is there at once): the probe decides.
                Device::Sim(Proc::start(&args, ""))
            },
            probe_req,
            answer,
        )
    }

    /// pymodbus' own RTU server (tests/py/stock_server.py, `ModbusSerialServer` with the
    /// RTU framer) on a pty pair of its own: a device that answers as fast as Python
    /// does, nothing paced.
    pub(super) fn pymodbus_rtu(baud: u32) -> Line {
        let speed = baud.to_string();
        Line::probed(
            |dev| {
                let args = ["--port", dev, "--framer", "rtu", "--baud", &speed];
                Device::Pymodbus(Py::start("stock_server.py", &args))
            },
            &serial_read("rtu", 1),
            serial_reply_len("rtu", 1),
        )
    }

    /// A pty pair with the device `start` puts on its far end (given that end's path),
    /// once it answers `probe_req` in `answer` bytes.
    fn probed(start: impl FnOnce(&str) -> Device, probe_req: &[u8], answer: usize) -> Line {
        let dir = tempdir();
        let socat = Socat::start(dir.path());
        let device = start(socat.dev.to_str().unwrap());
        let mut probe = RawLine::open(&socat.gw);
        let since = Instant::now();
        while probe.transact(probe_req, answer).len() < answer {
            assert!(
                since.elapsed() < Duration::from_secs(20),
                "the device never answered"
            );
        }
        Line {
            dir,
            socat,
            _sim: device,
        }
    }

    pub(super) fn raw(&self) -> RawLine {
        RawLine::open(&self.socat.gw)
    }

    /// `mbgate run` on this line: log at info, and the given `[relay]`/`[tcp]` lines.
    /// A pty has no USB adapter's latency: a lone MBAP reply is confirmed after 3.5
    /// character times, not the default `silence_floor_ms`.
    pub(super) fn gateway(&self, relay: &[&str], tcp: &[&str]) -> Gateway {
        let cfg = Cfg::new(&self.socat.gw).serial("silence_floor_ms = 0");
        self.gateway_with(cfg, relay, tcp)
    }

    /// [`Line::gateway`] from a configuration with `[serial]` lines of its own.
    pub(super) fn gateway_with(&self, cfg: Cfg, relay: &[&str], tcp: &[&str]) -> Gateway {
        let mut cfg = cfg.log_level("info");
        for l in relay {
            cfg = cfg.relay(l);
        }
        for l in tcp {
            cfg = cfg.tcp(l);
        }
        Gateway::start(&cfg, self.dir.path())
    }
}

/// A bare byte pipe in front of `line` (`socat TCP-LISTEN:0 FILE:pty`), and a master's
/// connection to it: what any path from a socket to the port costs, without framing.
pub(super) fn byte_pipe(line: &Line) -> (std::process::Child, TcpStream) {
    let (pipe, addr) = socat_pipe(&line.socat.gw);
    let s = TcpStream::connect(addr).expect("connect to socat");
    s.set_nodelay(true).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    (pipe, s)
}

pub(super) fn connect(gw: &Gateway) -> TcpStream {
    let s = gw.connect();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    s
}

/// One FC 03 round trip through the gateway; panics unless it is the normal reply.
pub(super) fn tcp_read(s: &mut TcpStream, tid: u16, qty: u16) -> Duration {
    let req = read_req(tid, 1, 0, qty);
    let t = Instant::now();
    s.write_all(&req).expect("send");
    let reply = read_frame(s);
    let took = t.elapsed();
    assert_eq!(
        (reply.len(), reply[7]),
        (reply_len(qty), 0x03),
        "not a normal reply: {reply:02X?}"
    );
    took
}

/// Runs `f` `n` times after `warm` unrecorded runs.
pub(super) fn samples(warm: usize, n: usize, mut f: impl FnMut(u16) -> Duration) -> Vec<Duration> {
    for i in 0..warm {
        f(i as u16);
    }
    (0..n).map(|i| f(i as u16)).collect()
}

/// A connection to `addr` whose first FC 03 read is answered: the simulator serves
/// one connection at a time, so this waits for the last one to be gone.
pub(super) fn served(addr: &str) -> TcpStream {
    let start = Instant::now();
    loop {
        if let Ok(mut s) = TcpStream::connect(addr) {
            s.set_nodelay(true).unwrap();
            s.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
            if s.write_all(&read_req(1, 1, 0, 1)).is_ok() {
                let mut head = [0u8; 1];
                if std::io::Read::read(&mut s, &mut head).unwrap_or(0) == 1 {
                    let mut rest = vec![0u8; reply_len(1) - 1];
                    std::io::Read::read_exact(&mut s, &mut rest).unwrap();
                    return s;
                }
            }
        }
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "{addr} never served"
        );
        thread::sleep(Duration::from_millis(50));
    }
}

// ---------------------------------------------------------------------------------
// Load loops

/// Transactions per second the wire allows: half duplex (one outstanding: request
/// then reply) or full duplex (pipelined: the longer direction limits).
pub(super) fn wire_limit(baud: u32, qty: u16, full_duplex: bool) -> f64 {
    let bytes = if full_duplex {
        REQ.max(reply_len(qty))
    } else {
        REQ + reply_len(qty)
    };
    f64::from(baud) / 10.0 / bytes as f64
}

/// Keeps `window` FC 03 reads outstanding (1 = polling) for `budget`, through
/// `send`/`recv` (which returns how many replies it read); returns transactions per
/// second between the last warm-up reply and the last reply before the deadline.
pub(super) fn throughput(
    window: usize,
    qty: u16,
    budget: Duration,
    mut send: impl FnMut(&[u8]),
    mut recv: impl FnMut() -> usize,
) -> f64 {
    const WARM: usize = 8;
    let mut tid = 0u16;
    let mut request = || {
        tid = tid.wrapping_add(1);
        read_req(tid, 1, 0, qty)
    };
    for _ in 0..window {
        send(&request());
    }
    let mut done = 0usize;
    let (mut start, mut last, mut counted) = (Instant::now(), Instant::now(), 0usize);
    let deadline = Instant::now() + budget;
    let mut sent = window;
    loop {
        let n = recv();
        for _ in 0..n {
            done += 1;
            let now = Instant::now();
            if done == WARM {
                start = now;
            } else if done > WARM && now <= deadline {
                (last, counted) = (now, counted + 1);
            }
            if now < deadline && sent < MAX_TRANSACTIONS {
                send(&request());
                sent += 1;
            }
        }
        if done == sent {
            break;
        }
    }
    // Replies after the deadline (the pipeline draining) are not counted.
    counted as f64 / (last - start).as_secs_f64()
}

/// Polls (or pipelines) through the gateway.
pub(super) fn tcp_throughput(s: &mut TcpStream, window: usize, qty: u16, budget: Duration) -> f64 {
    let mut rd = s.try_clone().unwrap();
    throughput(
        window,
        qty,
        budget,
        |req| s.write_all(req).expect("send"),
        || {
            let reply = read_frame(&mut rd);
            assert_eq!(
                reply.len(),
                reply_len(qty),
                "not a normal reply: {reply:02X?}"
            );
            1
        },
    )
}

// ---------------------------------------------------------------------------------
// A process's figures from /proc

/// A `kB` field of /proc/PID/status.
pub(super) fn proc_status(pid: u32, key: &str) -> u64 {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("status");
    s.lines()
        .find_map(|l| l.strip_prefix(&format!("{key}:")))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no {key} in /proc/{pid}/status"))
}

/// The peak-RSS target: at most 8 MiB (`kb` from VmHWM).
pub(super) fn peak_rss_row(r: &mut Report, scenario: &'static str, measure: &str, kb: u64) {
    r.row(
        scenario,
        measure,
        format!("{:.2} MiB", kb as f64 / 1024.0),
        "≤ 8 MiB",
        Some(kb <= 8 * 1024),
    );
}

/// utime + stime of a process, in clock ticks (/proc/PID/stat fields 14 and 15).
pub(super) fn cpu_ticks(pid: u32) -> u64 {
    let s = std::fs::read_to_string(format!("/proc/{pid}/stat")).expect("stat");
    // The command name may hold spaces; the fields after it are plain.
    let rest = &s[s.rfind(')').expect("comm") + 2..];
    let f: Vec<u64> = rest
        .split_whitespace()
        .map(|x| x.parse().unwrap_or(0))
        .collect();
    // rest starts at field 3 (state): field k is f[k - 3].
    f[14 - 3] + f[15 - 3]
}

pub(super) fn clock_ticks_per_second() -> u64 {
    // SAFETY: sysconf has no preconditions.
    (unsafe { libc::sysconf(libc::_SC_CLK_TCK) }).max(1) as u64
}

// ---------------------------------------------------------------------------------
// Serial framing

/// RTU bytes of the reply to an FC 03 read of `qty` registers: address, function, byte
/// count, 2 × qty, CRC.
pub(super) fn rtu_reply_len(qty: u16) -> usize {
    5 + 2 * usize::from(qty)
}

/// An FC 03 read of `qty` registers of unit 1 in `framing` ("rtu" or "ascii").
pub(super) fn serial_read(framing: &str, qty: u16) -> Vec<u8> {
    let pdu = [0x03, 0, 0, 0, qty as u8];
    match framing {
        "rtu" => mbgate::frame::rtu::encode(1, &pdu),
        _ => mbgate::frame::ascii::encode(1, &pdu),
    }
}

/// Bytes of the reply to [`serial_read`]: ASCII is `:`, two hex digits a byte of
/// unit, function, count, data and LRC, CR LF.
pub(super) fn serial_reply_len(framing: &str, qty: u16) -> usize {
    match framing {
        "rtu" => rtu_reply_len(qty),
        _ => 3 + 2 * (4 + 2 * usize::from(qty)),
    }
}

/// The simulator (`generic` profile) as a Modbus/TCP device on a free port of
/// 127.0.0.1, for the scenarios with a device on the network; it and its address.
pub(super) fn network_sim() -> (Proc, String) {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let at = format!("127.0.0.1:{port}");
    let sim = [
        "sim",
        "--listen",
        &at,
        "--profile",
        "generic",
        "--log-level",
        "warn",
        "--headless",
    ];
    (Proc::start(&sim, ""), at)
}
