//! The USB adapter pulled out and put back, on this machine's ptys (docs/raspberry-pi.md
//! "When the adapter is pulled out"; with the kernel's own driver in `scripts/pi-check`):
//! the port named as users name an adapter, by a by-id link that udev removes with its
//! directory when the adapter goes and makes again, to a new node, when it is back. The
//! device is pymodbus' RTU server on the far end of a socat pty pair; the masters are
//! pymodbus' and pipelining ones (tests/py/value_masters.py), every reply checked by
//! value.

use crate::common;
use common::*;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A USB adapter as udev shows it, played with ptys (the module notes).
struct Adapter {
    dir: PathBuf,
    /// `serial/by-id/usb-FTDI_...`, as the gateway is configured.
    link: PathBuf,
    socat: Option<Child>,
    device: Option<Py>,
    plugs: u32,
}

impl Adapter {
    fn new(dir: &Path) -> Adapter {
        Adapter {
            dir: dir.to_owned(),
            link: dir.join("serial/by-id/usb-FTDI_FT232R_USB_UART_A50285BI-if00-port0"),
            socat: None,
            device: None,
            plugs: 0,
        }
    }

    /// Plugs it in: a new pty pair, the device serving its far end, then the link to
    /// the gateway's end, as udev makes it once the node is there. Returns the node
    /// the link names and the instant it was made.
    fn plug(&mut self) -> (PathBuf, Instant) {
        self.prepare();
        self.link()
    }

    /// The pty pair and the device on it, no link yet.
    fn prepare(&mut self) {
        self.plugs += 1;
        let gw = self.dir.join(format!("pty-gw-{}", self.plugs));
        let dev = self.dir.join(format!("pty-dev-{}", self.plugs));
        let socat = Command::new("socat")
            .arg(format!("pty,raw,echo=0,link={}", gw.display()))
            .arg(format!("pty,raw,echo=0,link={}", dev.display()))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("socat");
        self.socat = Some(socat);
        wait_for("socat's ptys", Duration::from_secs(5), || {
            gw.exists() && dev.exists()
        });
        let dev = dev.display().to_string();
        self.device = Some(Py::start(
            "serial_device.py",
            &[
                "--port", &dev, "--framer", "rtu", "--baud", "19200", "--parity", "N", "--units",
                "1", "--size", "200",
            ],
        ));
        // pymodbus says READY as its serial transport starts, and may yet discard what
        // came before it reads: the link is made once it surely reads, so that the
        // first request after it is the device's to answer.
        std::thread::sleep(Duration::from_millis(500));
    }

    /// The link to the gateway's end of the pty pair made last, as udev makes it.
    fn link(&mut self) -> (PathBuf, Instant) {
        let gw = self.dir.join(format!("pty-gw-{}", self.plugs));
        let node = std::fs::read_link(&gw).unwrap();
        std::fs::create_dir_all(self.link.parent().unwrap()).unwrap();
        std::os::unix::fs::symlink(&node, &self.link).unwrap();
        (node, Instant::now())
    }

    /// Pulls it out: the link goes, and its directories with it (udev removes
    /// `by-id` with its last link), and the ptys vanish (socat ends).
    fn pull(&mut self) {
        std::fs::remove_file(&self.link).unwrap();
        std::fs::remove_dir(self.link.parent().unwrap()).unwrap();
        std::fs::remove_dir(self.dir.join("serial")).unwrap();
        if let Some(mut s) = self.socat.take() {
            let _ = s.kill();
            let _ = s.wait();
        }
        self.device = None;
    }
}

impl Drop for Adapter {
    fn drop(&mut self) {
        if let Some(mut s) = self.socat.take() {
            let _ = s.kill();
            let _ = s.wait();
        }
    }
}

/// The gateway's descriptors: how many, and how many are `node`.
fn fds(pid: u32, node: &Path) -> (usize, usize) {
    let links: Vec<PathBuf> = std::fs::read_dir(format!("/proc/{pid}/fd"))
        .unwrap()
        .flatten()
        .filter_map(|e| std::fs::read_link(e.path()).ok())
        .collect();
    let on = links.iter().filter(|l| l.as_path() == node).count();
    (links.len(), on)
}

fn threads(pid: u32) -> usize {
    std::fs::read_dir(format!("/proc/{pid}/task"))
        .unwrap()
        .count()
}

/// The gateway as this file runs it: RTU at 19200 baud on the adapter's link, the
/// metrics listener on.
fn gateway(dir: &Path, link: &Path) -> Gateway {
    let cfg = Cfg::new(link)
        .serial("framing = \"rtu\"")
        .serial("baud_rate = 19200")
        .serial("parity = \"none\"")
        .serial("flow_control = \"none\"")
        .relay("response_timeout_ms = 1000")
        .metrics("listen = \"127.0.0.1:0\"");
    Gateway::start(&cfg, dir)
}

/// Waits until the gateway, whose outage began `since`, has tried to open the port
/// at least `after` into it, then until its next attempt: the backoff's attempts are
/// 2 s apart by then, so a port back now is reopened at once only by a gateway that
/// watches for it, not by its next attempt.
fn just_after_an_attempt(gw: &Gateway, since: Instant, after: Duration) {
    let tries = |gw: &Gateway| gw.log().matches("still unavailable").count();
    while since.elapsed() < after {
        std::thread::sleep(Duration::from_millis(50));
    }
    let n = tries(gw);
    wait_for("the next attempt to open", Duration::from_secs(5), || {
        tries(gw) > n
    });
}

/// Until a read of holding register 7 is answered with its value: the time it took
/// from `from`. Every answer meanwhile must be 0x0A (no path to the device yet).
fn served_again(m: &mut std::net::TcpStream, tid: &mut u16, from: Instant) -> Duration {
    loop {
        *tid += 1;
        let got = transact(m, &read_req(*tid, 1, 7, 1));
        if got == read_reply(*tid, 1, &[1007]) {
            return from.elapsed();
        }
        assert_eq!(
            got,
            mbgate::frame::Adu::exception(*tid, 1, 3, 0x0A).as_bytes(),
            "while the port is away"
        );
        assert!(
            from.elapsed() < Duration::from_secs(10),
            "never served again"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Pulled out four times under masters, each time away for 3.5 s or more: the dead
/// descriptor is let go at once, every master gets 0x0A (0x0B for a request on the
/// wire) and keeps its connection, service is back within a second of the link
/// appearing (the gateway watches the by-id directory: with only the backoff's
/// attempts, 2 s apart by then, it took up to 2 s), no reply is wrong; descriptors,
/// threads and memory stay flat; the log says each outage once and its length, and
/// /metrics counts them and their time.
#[test]
fn a_pulled_adapter_is_let_go_answered_0x0a_and_served_within_a_second_of_its_link() {
    if !peer("socat", "socat") {
        return;
    }
    let dir = tempdir();
    let mut adapter = Adapter::new(dir.path());
    let (mut node, _) = adapter.plug();
    let gw = gateway(dir.path(), &adapter.link);
    gw.wait_log("serial port open", Duration::from_secs(10));
    let pid = gw.proc.pid();
    let out = dir.path().join("masters.jsonl");
    let port = gw.addr.port().to_string();
    let masters = Py::start(
        "value_masters.py",
        &[
            "--port",
            &port,
            "--pymodbus",
            "2",
            "--pipelined",
            "2",
            "--depth",
            "4",
            "--timeout",
            "3",
            "--out",
            out.to_str().unwrap(),
        ],
    );
    let mut probe = gw.connect();
    let mut tid = 0u16;
    served_again(&mut probe, &mut tid, Instant::now());

    let cycles = 4;
    let mut away = Vec::new();
    let mut flat = None;
    for cycle in 1..=cycles {
        std::thread::sleep(Duration::from_millis(700));
        assert!(fds(pid, &node).1 >= 1, "the port is open before the pull");
        let pulled = Instant::now();
        adapter.pull();
        wait_for("the dead descriptor let go", Duration::from_secs(2), || {
            fds(pid, &node).1 == 0
        });
        let lost = gw.log().matches("serial port lost").count();
        assert_eq!(lost, cycle, "each outage said once:\n{}", gw.log());
        adapter.prepare();
        just_after_an_attempt(&gw, pulled, Duration::from_millis(3500));
        let at;
        (node, at) = adapter.link();
        away.push(pulled.elapsed());
        let resumed = served_again(&mut probe, &mut tid, at);
        assert!(
            resumed < Duration::from_secs(1),
            "cycle {cycle}: served again {resumed:?} after the link appeared:\n{}",
            gw.log()
        );
        let now = (fds(pid, &node).0, threads(pid), mem(&gw).rss_kib);
        match flat {
            None => flat = Some(now),
            Some((fds0, threads0, rss0)) => {
                assert_eq!((now.0, now.1), (fds0, threads0), "descriptors, threads");
                assert!(now.2 < rss0 + 1024, "RSS {} KiB after {} KiB", now.2, rss0);
            }
        }
    }
    std::thread::sleep(Duration::from_millis(500));
    drop(masters);

    let log = gw.log();
    let said: Vec<f64> = log
        .lines()
        .filter(|l| l.contains("back after an outage of "))
        .filter_map(|l| l.split("outage_ms=").nth(1)?.trim().parse::<f64>().ok())
        .map(|ms| ms / 1000.0)
        .collect();
    assert_eq!(said.len(), cycles, "each return said once:\n{log}");
    for (s, a) in said.iter().zip(&away) {
        assert!(
            (*s - a.as_secs_f64()).abs() < 0.5,
            "an outage of {a:?} said as {s} s"
        );
    }
    assert_eq!(gw.metric("mbgate_line_outages"), cycles as f64);
    assert_eq!(gw.metric("mbgate_line_opens"), cycles as f64 + 1.0);
    let total: f64 = said.iter().sum();
    let counted = gw.metric("mbgate_line_outage_seconds");
    assert!(
        (counted - total).abs() < 0.1,
        "{counted} s counted, {total} s said"
    );

    let all = std::fs::read_to_string(&out).unwrap();
    let summary = all.lines().last().unwrap();
    let count = |kind: &str| {
        summary
            .split(&format!("\"{kind}\": "))
            .nth(1)
            .and_then(|r| r.split([',', '}']).next()?.parse::<u64>().ok())
            .unwrap_or(0)
    };
    assert!(count("ok") > 100, "{summary}");
    assert!(count("x0a") > 0, "the outages were answered: {summary}");
    for kind in ["wrong", "lost", "closed"] {
        assert_eq!(count(kind), 0, "{kind}: {summary}\n{all}");
    }
}

/// Started while the adapter is out: it serves 0x0A at once, counts the outage from
/// the start, and serves the device within a second of its link appearing.
#[test]
fn started_without_its_adapter_it_answers_0x0a_then_serves_it_within_a_second() {
    if !peer("socat", "socat") {
        return;
    }
    let dir = tempdir();
    let mut adapter = Adapter::new(dir.path());
    let started = Instant::now();
    let gw = gateway(dir.path(), &adapter.link);
    let mut m = gw.connect();
    let asked = Instant::now();
    assert_eq!(
        transact(&mut m, &read_req(1, 1, 7, 1)),
        mbgate::frame::Adu::exception(1, 1, 3, 0x0A).as_bytes()
    );
    assert!(asked.elapsed() < Duration::from_secs(1), "0x0A at once");
    adapter.prepare();
    just_after_an_attempt(&gw, started, Duration::from_millis(3500));
    let (_, at) = adapter.link();
    let mut tid = 1;
    let resumed = served_again(&mut m, &mut tid, at);
    assert!(
        resumed < Duration::from_secs(1),
        "served {resumed:?} after the link"
    );
    assert_eq!(gw.metric("mbgate_line_outages"), 1.0);
    let counted = gw.metric("mbgate_line_outage_seconds");
    assert!(counted >= 3.5, "{counted} s");
    assert_eq!(gw.log().matches("back after an outage of").count(), 1);
}

/// A node that fails without vanishing, as the tty layer's hangup leaves one (every
/// descriptor of it reads end of file and fails writes, the node stays): closed, opened
/// again at the backoff's first attempt, served. TIOCVHANGUP needs CAP_SYS_ADMIN: the
/// test runs as root, and skips otherwise.
#[test]
fn a_node_that_fails_without_vanishing_is_reopened() {
    if !peer("socat", "socat") {
        return;
    }
    let dir = tempdir();
    let mut adapter = Adapter::new(dir.path());
    let (node, _) = adapter.plug();
    let gw = gateway(dir.path(), &adapter.link);
    gw.wait_log("serial port open", Duration::from_secs(10));
    let mut m = gw.connect();
    let mut tid = 0;
    served_again(&mut m, &mut tid, Instant::now());
    let tty = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags(libc::O_NOCTTY | libc::O_NONBLOCK)
        .open(&node)
        .unwrap();
    use std::os::fd::AsRawFd;
    use std::os::unix::fs::OpenOptionsExt;
    // SAFETY: TIOCVHANGUP takes no argument; the descriptor is open.
    let r = unsafe { libc::ioctl(tty.as_raw_fd(), libc::TIOCVHANGUP as _) };
    if r != 0 {
        eprintln!("SKIP: TIOCVHANGUP: {}", std::io::Error::last_os_error());
        return;
    }
    drop(tty);
    let hung = Instant::now();
    gw.wait_log("serial port lost", Duration::from_secs(5));
    let resumed = served_again(&mut m, &mut tid, hung);
    assert!(
        resumed < Duration::from_secs(2),
        "served again after {resumed:?}"
    );
    assert!(node.exists(), "the node stayed");
    assert_eq!(gw.log().matches("back after an outage of").count(), 1);
    assert_eq!(gw.metric("mbgate_line_outages"), 1.0);
}
