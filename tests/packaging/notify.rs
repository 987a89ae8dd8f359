//! systemd's notify protocol: a test plays systemd,
//! listening on a NOTIFY_SOCKET datagram socket, and sees READY=1 once the gateway
//! listens, WATCHDOG=1 from the relay at half of WATCHDOG_USEC (only when asked), and
//! STOPPING=1 on SIGTERM, in that order; STATUS= refreshed with the line's numbers.
//! Notify failures are never fatal.

use crate::common;
use common::*;
use std::os::unix::net::UnixDatagram;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

/// The manager's end of NOTIFY_SOCKET: every datagram, with when it came.
struct Manager {
    path: PathBuf,
    got: Arc<Mutex<Vec<(Instant, String)>>>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl Manager {
    fn listen(dir: &Path) -> Manager {
        let path = dir.join("notify.sock");
        let sock = UnixDatagram::bind(&path).expect("bind the notify socket");
        sock.set_read_timeout(Some(Duration::from_millis(20)))
            .unwrap();
        let got = Arc::new(Mutex::new(Vec::new()));
        let stop = Arc::new(AtomicBool::new(false));
        let (got2, stop2) = (got.clone(), stop.clone());
        let thread = thread::spawn(move || {
            let mut buf = [0u8; 4096];
            while !stop2.load(Ordering::Relaxed) {
                if let Ok(n) = sock.recv(&mut buf) {
                    let msg = String::from_utf8_lossy(&buf[..n]).into_owned();
                    got2.lock().unwrap().push((Instant::now(), msg));
                }
            }
        });
        Manager {
            path,
            got,
            stop,
            thread: Some(thread),
        }
    }

    fn messages(&self) -> Vec<(Instant, String)> {
        self.got.lock().unwrap().clone()
    }

    /// Index of the first message with this `KEY=value` line.
    fn first(&self, line: &str) -> Option<usize> {
        self.messages()
            .iter()
            .position(|(_, m)| m.lines().any(|l| l == line))
    }

    /// Index of the first message with `line`, once there is one.
    fn wait_for(&self, line: &str, timeout: Duration) -> usize {
        wait_for(line, timeout, || self.first(line).is_some());
        self.first(line).expect("seen")
    }
}

impl Drop for Manager {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn is_watchdog(m: &str) -> bool {
    m.lines().any(|l| l == "WATCHDOG=1")
}

#[test]
fn ready_then_watchdog_from_the_relay_then_stopping() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let sd = Manager::listen(dir.path());
    // WATCHDOG_USEC = 400 ms: a ping every 200 ms.
    let launch = Launch::default()
        .env("NOTIFY_SOCKET", sd.path.to_str().unwrap())
        .env("WATCHDOG_USEC", "400000");
    // The default response timeout, which the drain's extension below counts.
    let cfg = Cfg::new(&socat.gw).relay("response_timeout_ms = 1000");
    let mut gw = Gateway::launch(&cfg, dir.path(), launch);
    let ready = sd.wait_for("READY=1", Duration::from_secs(5));
    let (_, first) = &sd.messages()[ready];
    assert!(
        first.contains(&format!("STATUS=listening on {}", gw.addr)),
        "{first:?}"
    );
    gw.wait_log("serial port open", Duration::from_secs(5));

    thread::sleep(Duration::from_millis(1300));
    let status = gw.terminate(Duration::from_secs(5));
    assert_eq!(status.code(), Some(0), "{}", gw.log());
    let stopping = sd.wait_for("STOPPING=1", Duration::from_secs(1));

    let msgs = sd.messages();
    assert_eq!(ready, 0, "READY=1 comes first: {msgs:?}");
    let pings: Vec<Instant> = msgs[..stopping]
        .iter()
        .filter(|(_, m)| is_watchdog(m))
        .map(|(t, _)| *t)
        .collect();
    // ~1.3 s of an idle gateway at one ping per 200 ms, the first at once.
    assert!(
        (5..=9).contains(&pings.len()),
        "{} pings before STOPPING=1: {msgs:?}",
        pings.len()
    );
    for pair in pings.windows(2) {
        let gap = pair[1] - pair[0];
        assert!(
            gap >= Duration::from_millis(150) && gap <= Duration::from_millis(600),
            "pings {gap:?} apart, want ~200 ms: {msgs:?}"
        );
    }
    // systemd is asked to wait for the drain: 1 s response timeout + 2 s + 1 s.
    let (_, stop) = &msgs[stopping];
    assert!(
        stop.lines().any(|l| l == "EXTEND_TIMEOUT_USEC=4000000"),
        "{stop:?}"
    );
}

#[test]
fn no_watchdog_pings_unless_asked_for_this_process() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    for (i, launch) in [
        Launch::default(),
        // WATCHDOG_PID names another process: the watchdog is not ours.
        Launch::default()
            .env("WATCHDOG_USEC", "100000")
            .env("WATCHDOG_PID", "1"),
    ]
    .into_iter()
    .enumerate()
    {
        let sd_dir = dir.path().join(format!("manager{i}"));
        std::fs::create_dir(&sd_dir).unwrap();
        let sd = Manager::listen(&sd_dir);
        let launch = launch.env("NOTIFY_SOCKET", sd.path.to_str().unwrap());
        let mut gw = Gateway::launch(&Cfg::new(&socat.gw), dir.path(), launch);
        sd.wait_for("READY=1", Duration::from_secs(5));
        thread::sleep(Duration::from_millis(500));
        assert_eq!(gw.terminate(Duration::from_secs(5)).code(), Some(0));
        sd.wait_for("STOPPING=1", Duration::from_secs(1));
        let msgs = sd.messages();
        assert_eq!(msgs.len(), 2, "only READY=1 and STOPPING=1: {msgs:?}");
        assert!(!msgs.iter().any(|(_, m)| is_watchdog(m)), "{msgs:?}");
    }
}

#[test]
fn a_notify_socket_nobody_listens_on_is_not_fatal() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let _dev = RawDevice::start(&socat.dev, register_device(&[1], Duration::ZERO));
    let launch = Launch::default()
        .env("NOTIFY_SOCKET", dir.path().join("nobody").to_str().unwrap())
        .env("WATCHDOG_USEC", "100000");
    let mut gw = Gateway::launch(&Cfg::new(&socat.gw), dir.path(), launch);
    gw.wait_log("serial port open", Duration::from_secs(5));
    let mut m = gw.connect();
    assert_eq!(
        transact(&mut m, &read_req(1, 1, 7, 1)),
        read_reply(1, 1, &[7])
    );
    thread::sleep(Duration::from_millis(300));
    assert_eq!(gw.terminate(Duration::from_secs(5)).code(), Some(0));
    let log = gw.log();
    assert_eq!(
        log.matches("cannot notify systemd (NOTIFY_SOCKET)").count(),
        1,
        "warned once, then quiet: {log}"
    );
}

/// `systemctl status` tells the story: STATUS= is refreshed every 2 s with the masters,
/// the request rate, the last reply's age and the timeouts of the last minute.
#[test]
fn status_is_refreshed_with_masters_rate_last_reply_and_timeouts() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let _dev = RawDevice::start(&socat.dev, register_device(&[1], Duration::ZERO));
    let sd = Manager::listen(dir.path());
    let launch = Launch::default().env("NOTIFY_SOCKET", sd.path.to_str().unwrap());
    let cfg = Cfg::new(&socat.gw)
        .pty_line()
        .serial("flow_control = \"none\"")
        .relay("response_timeout_ms = 100");
    let mut gw = Gateway::launch(&cfg, dir.path(), launch);
    gw.wait_log("serial port open", Duration::from_secs(5));
    let mut a = gw.connect();
    let _b = gw.connect();
    for tid in 0..10 {
        assert_eq!(
            transact(&mut a, &read_req(tid, 1, 7, 1)),
            read_reply(tid, 1, &[7])
        );
    }
    // Unit 2 does not answer: one timeout.
    assert_eq!(
        transact(&mut a, &read_req(10, 2, 7, 1)),
        hex("00 0A 00 00 00 03 02 83 0B")
    );
    let refreshed = |m: &str| m.starts_with("STATUS=2 masters, ");
    wait_for("a STATUS= refresh", Duration::from_secs(5), || {
        sd.messages().iter().any(|(_, m)| refreshed(m))
    });
    let msgs = sd.messages();
    let (_, status) = msgs.iter().find(|(_, m)| refreshed(m)).unwrap();
    // "2 masters, 4.9 req/s, last reply 812 ms ago, 1 timeout in the last minute":
    // 11 requests within the first 2 s.
    let rest = status.strip_prefix("STATUS=2 masters, ").unwrap();
    let (rate, rest) = rest.split_once(" req/s, last reply ").expect(status);
    let rate: f64 = rate.parse().expect(status);
    assert!((2.0..=11.0).contains(&rate), "{status}");
    let (ago, rest) = rest.split_once(" ago, ").expect(status);
    assert!(ago.ends_with(" ms") || ago.ends_with(" s"), "{status}");
    assert_eq!(rest.trim_end(), "1 timeout in the last minute", "{status}");
    assert_eq!(gw.terminate(Duration::from_secs(5)).code(), Some(0));
}
