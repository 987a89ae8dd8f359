//! Real peers for the end-to-end tests: socat pty pairs, the mbgate binary, pymodbus
//! processes, a scriptable raw device on a pty, and a raw TCP master.
#![allow(dead_code)]

pub(crate) mod forge;
pub(crate) mod pki;
pub(crate) mod sim;

use mbgate::frame::mbap::decode_strict;
use mbgate::frame::Adu;
use std::io::{BufRead, BufReader, ErrorKind, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::os::fd::AsRawFd;
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

pub(crate) fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The venv interpreter with the pinned pymodbus (`scripts/test` creates it).
pub(crate) fn python() -> PathBuf {
    let p = std::env::var_os("MBGATE_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo().join(".venv/bin/python"));
    assert!(
        p.exists(),
        "{} not found: run scripts/test, which creates the venv with the pinned pymodbus",
        p.display()
    );
    p
}

/// A port nobody listens on now (for a device started later, or restarted there).
pub(crate) fn free_port() -> u16 {
    let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    l.local_addr().unwrap().port()
}

/// `mbgate run` with this configuration file's text (written to `dir`); the addresses
/// of its first `listeners` listeners, in the order it logs them.
pub(crate) fn gateway_from_file(
    dir: &Path,
    text: &str,
    listeners: usize,
) -> (Proc, Vec<std::net::SocketAddr>) {
    let file = dir.join("mbgate.toml");
    std::fs::write(&file, text).unwrap();
    let proc = Proc::start(
        &["run", "--config", file.to_str().unwrap()],
        "listening on ",
    );
    wait_for("every listener", Duration::from_secs(10), || {
        proc.log().matches("listening on ").count() >= listeners
    });
    let addrs = proc
        .log()
        .split("listening on ")
        .skip(1)
        .map(|rest| rest.split_whitespace().next().unwrap().parse().unwrap())
        .collect();
    (proc, addrs)
}

/// A UDP port no socket holds now.
pub(crate) fn free_udp_port() -> u16 {
    let s = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    s.local_addr().unwrap().port()
}

/// One datagram to `to` from a new socket connected to it, and its reply within 10 s;
/// `Err` when none comes, or when nobody listens there (the ICMP port unreachable the
/// kernel turns into ConnectionRefused).
pub(crate) fn udp_transact(to: &str, req: &[u8]) -> std::io::Result<Vec<u8>> {
    let s = std::net::UdpSocket::bind("127.0.0.1:0")?;
    s.connect(to)?;
    s.set_read_timeout(Some(Duration::from_secs(10)))?;
    s.send(req)?;
    let mut buf = [0u8; 300];
    let n = s.recv(&mut buf)?;
    Ok(buf[..n].to_vec())
}

/// `"00 01 FF"` → bytes.
pub(crate) fn hex(s: &str) -> Vec<u8> {
    let s: String = s.split_whitespace().collect();
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&s[i..i + 2], 16).expect("hex"))
        .collect()
}

pub(crate) fn tempdir() -> tempfile::TempDir {
    tempfile::Builder::new()
        .prefix("mbgate-test-")
        .tempdir()
        .expect("temp dir")
}

/// Whether the command `command` is installed (on PATH). When it is not, the calling
/// test is to return at once: this says so on stderr, naming the Debian package that
/// has it, and adds a line to the file `$MBGATE_SKIPS`, which scripts/test counts as a
/// skip in its summary (scripts/test --no-install installs nothing). In CI (CI=true)
/// everything is installed, and a missing command fails the test.
pub(crate) fn peer(command: &str, package: &str) -> bool {
    let found = std::env::var_os("PATH").is_some_and(|path| {
        std::env::split_paths(&path).any(|dir| {
            use std::os::unix::fs::PermissionsExt;
            std::fs::metadata(dir.join(command))
                .is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o111 != 0)
        })
    });
    if found {
        return true;
    }
    assert!(
        std::env::var("CI").as_deref() != Ok("true"),
        "{command} is missing in CI, where scripts/test installs every Debian package \
         (this one: {package})"
    );
    skipped(&format!("needs {command} (Debian package {package})"));
    false
}

/// The calling test skips, for `why`: said on stderr and added to `$MBGATE_SKIPS`,
/// which scripts/test counts in its summary.
pub(crate) fn skipped(why: &str) {
    let test = std::thread::current().name().unwrap_or("?").to_owned();
    let line = format!("{test}: {why}");
    eprintln!("skipped: {line}");
    if let Some(file) = std::env::var_os("MBGATE_SKIPS") {
        let mut f = std::fs::OpenOptions::new()
            .append(true)
            .create(true)
            .open(file)
            .expect("open $MBGATE_SKIPS");
        // `BINARY MODULE::TEST: why` (scripts/test counts a test once by what comes
        // before the first ": ").
        writeln!(f, "{} {line}", env!("CARGO_CRATE_NAME")).unwrap();
    }
}

/// Polls `ok` every 10 ms until it holds; fails the test after `timeout`.
pub(crate) fn wait_for(what: &str, timeout: Duration, mut ok: impl FnMut() -> bool) {
    let start = Instant::now();
    while !ok() {
        assert!(start.elapsed() < timeout, "timed out waiting for {what}");
        thread::sleep(Duration::from_millis(10));
    }
}

fn terminate(child: &mut Child) {
    signal(child, "TERM");
}

fn signal(child: &mut Child, name: &str) {
    let _ = Command::new("kill")
        .arg(format!("-{name}"))
        .arg(child.id().to_string())
        .status();
}

// ---------------------------------------------------------------------------------
// One run of the binary to completion

/// What one run of the binary did.
#[derive(Debug)]
pub(crate) struct Run {
    pub(crate) code: i32,
    pub(crate) stdout: String,
    pub(crate) stderr: String,
    pub(crate) elapsed: Duration,
}

impl Run {
    pub(crate) fn lines(&self) -> Vec<&str> {
        self.stdout.lines().collect()
    }
}

/// Runs `mbgate ARGS`, bounded: a run that takes more than 30 s is killed and fails.
pub(crate) fn mbgate(args: &[&str]) -> Run {
    let start = Instant::now();
    let (mut cmd, stderr) = Launch::default().command(args);
    let mut child = cmd.spawn().expect("run mbgate");
    drop(cmd);
    let drain = |mut r: Box<dyn Read + Send>| {
        thread::spawn(move || {
            let mut s = String::new();
            let _ = r.read_to_string(&mut s);
            s
        })
    };
    let out = drain(Box::new(child.stdout.take().unwrap()));
    let err = drain(Box::new(stderr));
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if start.elapsed() > Duration::from_secs(30) {
            let _ = child.kill();
            let _ = child.wait();
            panic!("mbgate {args:?} did not finish within 30 s");
        }
        thread::sleep(Duration::from_millis(5));
    };
    let run = Run {
        code: status.code().expect("exit code, not a signal"),
        stdout: out.join().unwrap(),
        stderr: err.join().unwrap(),
        elapsed: start.elapsed(),
    };
    eprintln!(
        "$ mbgate {}\n{}{}(exit {}, {:?})",
        args.join(" "),
        run.stdout,
        run.stderr,
        run.code,
        run.elapsed
    );
    run
}

// ---------------------------------------------------------------------------------
// socat

/// `socat TCP-LISTEN:0 FILE:PTY`: the least any TCP-to-serial process can add (a
/// byte pipe, no framing), as a second baseline. Returns it and its address.
pub(crate) fn socat_pipe(pty: &Path) -> (std::process::Child, std::net::SocketAddr) {
    socat_to(&format!("FILE:{},raw,echo=0", pty.display()))
}

/// `socat TCP-LISTEN:0 FAR`: a bare byte pipe to `FAR` (a pty, a TCP address).
pub(crate) fn socat_to(far: &str) -> (std::process::Child, std::net::SocketAddr) {
    use std::io::BufRead;
    let mut child = std::process::Command::new("socat")
        .args(["-d", "-d", "TCP-LISTEN:0,bind=127.0.0.1", far])
        .stdin(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("socat");
    let mut lines = std::io::BufReader::new(child.stderr.take().unwrap()).lines();
    // "... listening on AF=2 127.0.0.1:PORT"; stderr closes if socat fails.
    let addr = lines
        .by_ref()
        .map_while(Result::ok)
        .find_map(|l| {
            l.split("listening on AF=2 ")
                .nth(1)
                .and_then(|a| a.trim().parse().ok())
        })
        .expect("socat's listening address");
    thread::spawn(move || lines.for_each(drop));
    (child, addr)
}

/// A virtual serial cable: `gw` is the gateway's end, `dev` the device's.
pub(crate) struct Socat {
    child: Option<Child>,
    pub(crate) gw: PathBuf,
    pub(crate) dev: PathBuf,
}

impl Socat {
    pub(crate) fn start(dir: &Path) -> Socat {
        let mut s = Socat {
            child: None,
            gw: dir.join("gw"),
            dev: dir.join("dev"),
        };
        s.restart();
        s
    }

    pub(crate) fn restart(&mut self) {
        self.stop();
        let child = Command::new("socat")
            .arg(format!("pty,raw,echo=0,link={}", self.gw.display()))
            .arg(format!("pty,raw,echo=0,link={}", self.dev.display()))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("socat (apt-get install socat; scripts/test does)");
        self.child = Some(child);
        let (gw, dev) = (self.gw.clone(), self.dev.clone());
        wait_for("socat links", Duration::from_secs(5), || {
            gw.exists() && dev.exists()
        });
    }

    /// Pulls the cable: socat exits and both ptys vanish.
    pub(crate) fn stop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
        let _ = std::fs::remove_file(&self.gw);
        let _ = std::fs::remove_file(&self.dev);
    }
}

impl Drop for Socat {
    fn drop(&mut self) {
        self.stop();
    }
}

// ---------------------------------------------------------------------------------
// The gateway

/// Builds a configuration file: listen on 127.0.0.1:0, the given serial path, and
/// extra `key = value` lines per section.
#[derive(Clone)]
pub(crate) struct Cfg {
    serial: Vec<String>,
    tcp: Vec<String>,
    relay: Vec<String>,
    log: Vec<String>,
    /// The `[metrics]` section, written only when it has a line.
    metrics: Vec<String>,
    /// The `[control]` section, written only when it has a line.
    control: Vec<String>,
}

impl Cfg {
    pub(crate) fn new(serial_path: &Path) -> Cfg {
        Cfg {
            serial: vec![format!("path = {:?}", serial_path.display().to_string())],
            tcp: vec!["listen = \"127.0.0.1:0\"".into()],
            relay: vec![],
            log: vec!["level = \"debug\"".into()],
            metrics: vec![],
            control: vec![],
        }
    }
    pub(crate) fn serial(mut self, line: &str) -> Cfg {
        self.serial.push(line.into());
        self
    }
    pub(crate) fn tcp(mut self, line: &str) -> Cfg {
        self.tcp.push(line.into());
        self
    }
    pub(crate) fn relay(mut self, line: &str) -> Cfg {
        self.relay.push(line.into());
        self
    }
    pub(crate) fn log(mut self, line: &str) -> Cfg {
        self.log.push(line.into());
        self
    }
    pub(crate) fn metrics(mut self, line: &str) -> Cfg {
        self.metrics.push(line.into());
        self
    }
    pub(crate) fn control(mut self, line: &str) -> Cfg {
        self.control.push(line.into());
        self
    }
    /// A pty as the line, at the fastest speed there is: bytes go through as fast as
    /// they are written, and a pause of 3.5 characters (1.75 ms) ends a frame. (The
    /// gateway finds the pty has no wire at any `baud_rate`: docs/reliability.md
    /// "Knowing the wire"; `tests/e2e/third_party.rs` runs the default speeds.)
    pub(crate) fn pty_line(self) -> Cfg {
        self.serial("baud_rate = 4000000")
    }
    /// Replaces the log level (`debug` unless set).
    pub(crate) fn log_level(mut self, level: &str) -> Cfg {
        self.log[0] = format!("level = {level:?}");
        self
    }
    pub(crate) fn render(&self) -> String {
        let mut s = String::new();
        // A test that does not set the response timeout gets one far beyond what a
        // loaded machine adds to a device's answer (the default, 1 s, was missed with
        // a busy loop on each core beside five test runs): who gets which bytes does
        // not depend on how busy the machine is. A test about timeouts sets its own.
        let mut relay = self.relay.clone();
        if !relay
            .iter()
            .any(|l| l.trim_start().starts_with("response_timeout_ms"))
        {
            relay.push("response_timeout_ms = 5000".into());
        }
        // MBGATE_TEST_UNITS=auto: the same line in the [[line]] form, every unit's
        // response timeout learned (`response_timeout_ms = "auto"`, the line's as its
        // ceiling), to run a test file's scenarios with learned timeouts on
        // (docs/reliability.md "Learned timeouts").
        if std::env::var("MBGATE_TEST_UNITS").as_deref() == Ok("auto") {
            s += &format!(
                "[[line]]\n[line.serial]\n{}\n[line.relay]\n{}\n\
                 [[line.unit]]\nunits = \"1-255\"\nresponse_timeout_ms = \"auto\"\n\n",
                self.serial.join("\n"),
                relay.join("\n")
            );
        }
        let units = !s.is_empty();
        for (name, lines) in [
            ("serial", &self.serial),
            ("tcp", &self.tcp),
            ("relay", &relay),
            ("log", &self.log),
            ("metrics", &self.metrics),
            ("control", &self.control),
        ] {
            if units && matches!(name, "serial" | "relay") {
                continue;
            }
            if !matches!(name, "metrics" | "control") || !lines.is_empty() {
                s += &format!("[{name}]\n{}\n\n", lines.join("\n"));
            }
        }
        s
    }
}

/// An `mbgate` subcommand running as a child, stderr captured as its log.
pub(crate) struct Proc {
    child: Child,
    log: Arc<Mutex<String>>,
    /// From spawning to the first log line that showed `ready`.
    ready_after: Arc<Mutex<Option<Duration>>>,
    reader: Option<JoinHandle<()>>,
    pub(crate) stdout: Arc<Mutex<String>>,
}

/// How an `mbgate` process is started, beyond its arguments: the environment
/// systemd would give it. By default none of it (the variables are removed).
#[derive(Default)]
pub(crate) struct Launch {
    env: Vec<(&'static str, String)>,
    journal_stream: bool,
    /// Another mbgate binary than this tree's (a benchmark's baseline).
    program: Option<PathBuf>,
}

/// The variables systemd sets that change how mbgate behaves.
const SERVICE_ENV: [&str; 5] = [
    "RUST_LOG",
    "NOTIFY_SOCKET",
    "WATCHDOG_USEC",
    "WATCHDOG_PID",
    "JOURNAL_STREAM",
];

impl Launch {
    pub(crate) fn env(mut self, key: &'static str, value: impl Into<String>) -> Launch {
        self.env.push((key, value.into()));
        self
    }

    /// Runs `program` instead of this tree's mbgate (a benchmark's baseline build).
    pub(crate) fn program(mut self, program: impl Into<PathBuf>) -> Launch {
        self.program = Some(program.into());
        self
    }

    /// Sets JOURNAL_STREAM to the `dev:inode` of the gateway's stderr, as systemd
    /// does when the unit's output goes to the journal.
    pub(crate) fn journal_stream(mut self) -> Launch {
        self.journal_stream = true;
        self
    }

    /// `mbgate ARGS` in this environment, stdin closed, stdout piped, stderr on a pipe
    /// whose read end comes back. Drop the command once spawned, so the pipe closes
    /// when mbgate exits.
    pub(crate) fn command<S: AsRef<std::ffi::OsStr>>(
        &self,
        args: impl IntoIterator<Item = S>,
    ) -> (Command, std::io::PipeReader) {
        use std::os::unix::fs::MetadataExt;
        let (stderr, writer) = std::io::pipe().expect("pipe");
        let writer = std::fs::File::from(std::os::fd::OwnedFd::from(writer));
        let program = self.program.as_deref();
        let mut cmd = Command::new(program.unwrap_or(Path::new(env!("CARGO_BIN_EXE_mbgate"))));
        cmd.args(args);
        for key in SERVICE_ENV {
            cmd.env_remove(key);
        }
        if self.journal_stream {
            let st = writer.metadata().expect("fstat the stderr pipe");
            cmd.env("JOURNAL_STREAM", format!("{}:{}", st.dev(), st.ino()));
        }
        cmd.envs(self.env.iter().map(|(k, v)| (k, v)));
        cmd.stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(writer);
        (cmd, stderr)
    }
}

impl Proc {
    /// Starts `mbgate ARGS` and waits until its log shows `ready`.
    pub(crate) fn start(args: &[&str], ready: &str) -> Proc {
        Proc::launch(args, ready, &Launch::default())
    }

    /// [`Proc::start`] in the environment `launch` describes.
    pub(crate) fn launch(args: &[&str], ready: &str, launch: &Launch) -> Proc {
        let spawned = Instant::now();
        let (mut cmd, err) = launch.command(args);
        let mut child = cmd.spawn().expect("start mbgate");
        drop(cmd);
        let log = Arc::new(Mutex::new(String::new()));
        let stdout = Arc::new(Mutex::new(String::new()));
        let ready_after = Arc::new(Mutex::new(None));
        let out = child.stdout.take().unwrap();
        let sink = log.clone();
        let (seen, needle) = (ready_after.clone(), ready.to_string());
        let reader = thread::spawn(move || {
            for line in BufReader::new(err).lines() {
                let Ok(line) = line else { break };
                if line.contains(&needle) {
                    seen.lock().unwrap().get_or_insert(spawned.elapsed());
                }
                let mut l = sink.lock().unwrap();
                l.push_str(&line);
                l.push('\n');
            }
        });
        let sink = stdout.clone();
        thread::spawn(move || {
            for line in BufReader::new(out).lines() {
                let Ok(line) = line else { break };
                let mut l = sink.lock().unwrap();
                l.push_str(&line);
                l.push('\n');
            }
        });
        let p = Proc {
            child,
            log,
            ready_after,
            reader: Some(reader),
            stdout,
        };
        p.wait_log(ready, Duration::from_secs(10));
        p
    }

    pub(crate) fn log(&self) -> String {
        self.log.lock().unwrap().clone()
    }

    /// The child's process id (for /proc/PID: memory, state).
    pub(crate) fn pid(&self) -> u32 {
        self.child.id()
    }

    /// How long after spawning the `ready` line of [`Proc::start`] was read.
    pub(crate) fn ready_after(&self) -> Duration {
        self.ready_after.lock().unwrap().expect("started")
    }

    pub(crate) fn wait_log(&self, needle: &str, timeout: Duration) {
        let start = Instant::now();
        while !self.log().contains(needle) {
            assert!(
                start.elapsed() < timeout,
                "log never showed {needle:?}:\n{}",
                self.log()
            );
            thread::sleep(Duration::from_millis(10));
        }
    }

    /// The `[metrics]` listener's address, from the log line that names it (http or
    /// https), once it has shown within `within`.
    pub(crate) fn metrics_addr(&self, within: Duration) -> SocketAddr {
        self.wait_log("metrics on http", within);
        let log = self.log();
        let rest = log.split("metrics on http").nth(1).unwrap();
        let rest = rest.trim_start_matches('s').trim_start_matches("://");
        rest.split('/').next().unwrap().parse().unwrap()
    }

    /// Sends the signal `name` (`kill -NAME`) and carries on.
    pub(crate) fn signal(&mut self, name: &str) {
        signal(&mut self.child, name);
    }

    /// SIGTERM, then waits (bounded) for the exit.
    pub(crate) fn terminate(&mut self, within: Duration) -> ExitStatus {
        self.stop_with("TERM", within)
    }

    /// Sends the signal `name` (`kill -NAME`) and waits for the exit, at most `within`.
    pub(crate) fn stop_with(&mut self, name: &str, within: Duration) -> ExitStatus {
        signal(&mut self.child, name);
        let start = Instant::now();
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                if let Some(r) = self.reader.take() {
                    let _ = r.join();
                }
                return status;
            }
            assert!(
                start.elapsed() < within,
                "no exit within {within:?}:\n{}",
                self.log()
            );
            thread::sleep(Duration::from_millis(10));
        }
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `mbgate run` with a configuration file, on 127.0.0.1 port 0: `addr` is the port it
/// got.
pub(crate) struct Gateway {
    pub(crate) proc: Proc,
    pub(crate) addr: SocketAddr,
}

impl Gateway {
    pub(crate) fn start(cfg: &Cfg, dir: &Path) -> Gateway {
        Gateway::launch(cfg, dir, Launch::default())
    }

    pub(crate) fn launch(cfg: &Cfg, dir: &Path, launch: Launch) -> Gateway {
        Gateway::launch_text(&cfg.render(), dir, launch)
    }

    /// `mbgate run` with the configuration file `text` (either form, docs/design.md
    /// §4 and §4.1, in `dir`); `addr` is its first listener's address.
    pub(crate) fn launch_text(text: &str, dir: &Path, launch: Launch) -> Gateway {
        let file = dir.join("mbgate.toml");
        std::fs::write(&file, text).expect("write config");
        let args = ["run", "--config", file.to_str().unwrap()];
        let proc = Proc::launch(&args, "listening on ", &launch);
        let log = proc.log();
        let addr = log
            .split("listening on ")
            .nth(1)
            .and_then(|rest| rest.split_whitespace().next())
            .and_then(|a| a.parse().ok())
            .unwrap_or_else(|| panic!("no listen address in the log:\n{log}"));
        Gateway { proc, addr }
    }

    pub(crate) fn log(&self) -> String {
        self.proc.log()
    }

    /// Waits until the log contains `needle`.
    pub(crate) fn wait_log(&self, needle: &str, timeout: Duration) {
        self.proc.wait_log(needle, timeout)
    }

    pub(crate) fn connect(&self) -> TcpStream {
        let s = TcpStream::connect(self.addr).expect("connect to mbgate");
        // Against a hang, not a measure: a loaded machine can take seconds.
        s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
        s.set_nodelay(true).unwrap();
        s
    }

    /// The body of `path` on the gateway's `[metrics]` listener, read now.
    pub(crate) fn http_get(&self, path: &str) -> String {
        let addr = self.proc.metrics_addr(Duration::from_secs(10));
        let mut s = TcpStream::connect(addr).expect("connect to the metrics listener");
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        write!(
            s,
            "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
        )
        .unwrap();
        let mut all = String::new();
        s.read_to_string(&mut all).unwrap();
        let (_, body) = all.split_once("\r\n\r\n").expect("an HTTP reply");
        body.to_owned()
    }

    /// The sum of every sample of the metric `name` (its `_total` included) on the
    /// gateway's `[metrics]` listener (`listen = "127.0.0.1:0"`), read now: for a test
    /// that waits until a count is reached instead of sleeping a guess.
    pub(crate) fn metric(&self, name: &str) -> f64 {
        let all = self.http_get("/metrics");
        all.lines()
            .filter(|l| {
                l.strip_prefix(name)
                    .is_some_and(|rest| rest.starts_with(['{', ' ']) || rest.starts_with("_total"))
            })
            .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
            .sum()
    }

    /// SIGTERM, then waits (bounded) for the exit; the log is complete afterwards.
    pub(crate) fn terminate(&mut self, within: Duration) -> ExitStatus {
        self.proc.terminate(within)
    }

    /// SIGTERM; the gateway must exit 0. Returns the counters it logs on exit.
    pub(crate) fn stop(&mut self) -> std::collections::HashMap<String, u64> {
        let status = self.terminate(Duration::from_secs(10));
        let log = self.log();
        assert!(status.success(), "exit {status:?}:\n{log}");
        let line = log
            .lines()
            .rev()
            .find(|l| l.contains("stopped") && l.contains("connections_refused="))
            .unwrap_or_else(|| panic!("no counters in the log:\n{log}"));
        line.split_whitespace()
            .filter_map(|token| {
                let (key, value) = token.rsplit_once('=')?;
                let key = key.rsplit('=').next()?;
                Some((key.to_string(), value.parse().ok()?))
            })
            .collect()
    }
}

// ---------------------------------------------------------------------------------
// Python peers

pub(crate) struct Py {
    child: Child,
}

impl Py {
    /// Runs `tests/py/<script>` and waits for it to print READY.
    pub(crate) fn start(script: &str, args: &[&str]) -> Py {
        let mut child = Command::new(python())
            .arg(repo().join("tests/py").join(script))
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("start python");
        let mut out = BufReader::new(child.stdout.take().unwrap());
        let (tx, rx) = mpsc::channel();
        thread::spawn(move || {
            let mut line = String::new();
            let _ = out.read_line(&mut line);
            let _ = tx.send(line);
            // Keep draining so the child never blocks on a full pipe.
            let _ = std::io::copy(&mut out, &mut std::io::sink());
        });
        let line = rx.recv_timeout(Duration::from_secs(20)).unwrap_or_default();
        assert_eq!(line.trim(), "READY", "{script} did not start");
        Py { child }
    }

    /// Runs a script to completion: (exit status, stdout).
    pub(crate) fn run(script: &str, args: &[&str]) -> (ExitStatus, String) {
        let out = Command::new(python())
            .arg(repo().join("tests/py").join(script))
            .args(args)
            .stderr(Stdio::inherit())
            .output()
            .expect("run python");
        (
            out.status,
            String::from_utf8_lossy(&out.stdout).into_owned(),
        )
    }
}

impl Drop for Py {
    fn drop(&mut self) {
        terminate(&mut self.child);
        let start = Instant::now();
        while start.elapsed() < Duration::from_secs(3) {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            thread::sleep(Duration::from_millis(10));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

// ---------------------------------------------------------------------------------
// A raw device on the pty, scripted by the test

/// What the raw device does with each request it receives.
pub(crate) type Handler = Box<dyn FnMut(&Adu) -> Vec<u8> + Send>;

/// A device on the `dev` end of a socat pair that decodes MBAP requests and writes
/// whatever the handler returns (nothing = no answer). Every request is recorded, and
/// every byte the line brought, whatever it was.
pub(crate) struct RawDevice {
    stop: Arc<AtomicBool>,
    file: std::fs::File,
    pub(crate) seen: Arc<Mutex<Vec<Adu>>>,
    got: Arc<Mutex<Vec<u8>>>,
    thread: Option<JoinHandle<()>>,
}

/// Opens a pty end for raw, non-blocking reads and writes.
pub(crate) fn open_pty(path: &Path) -> std::fs::File {
    std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags(libc::O_NONBLOCK | libc::O_NOCTTY)
        .open(path)
        .unwrap_or_else(|e| {
            let held = mbgate::line::port::serial::held_by(&path.to_string_lossy());
            panic!("open pty {}: {e}{held}", path.display())
        })
}

/// A thread that reads `file` until `stop`, handing `step` the bytes read (none when
/// nothing came for a millisecond), the time since the last byte, and the file to
/// answer on; `step` returns false to end.
fn pump(
    file: &std::fs::File,
    stop: Arc<AtomicBool>,
    mut step: impl FnMut(&[u8], Duration, &mut std::fs::File) -> bool + Send + 'static,
) -> JoinHandle<()> {
    let mut rd = file.try_clone().unwrap();
    let mut wr = file.try_clone().unwrap();
    thread::spawn(move || {
        // A scripted pause is a premise of its test (shorter than the pause that ends
        // a frame): at real-time priority where the test may set it (root, as CI runs
        // it), a busy machine cannot stretch it; refused, the thread runs as it was.
        let param = libc::sched_param { sched_priority: 1 };
        // SAFETY: `param` is valid for the call; 0 is this thread.
        unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) };
        let mut chunk = [0u8; 1024];
        let mut last = Instant::now();
        while !stop.load(Ordering::Relaxed) {
            let n = match rd.read(&mut chunk) {
                Ok(0) => break,
                Ok(n) => {
                    last = Instant::now();
                    n
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock => {
                    thread::sleep(Duration::from_millis(1));
                    0
                }
                Err(_) => break,
            };
            if !step(&chunk[..n], last.elapsed(), &mut wr) {
                break;
            }
        }
    })
}

/// What a scripted MBAP device writes for each request: pieces of bytes, each written
/// that long after the request was read (in order), so a test can put a pause exactly
/// where it wants one.
pub(crate) type MbapScript = Box<dyn FnMut(&Adu) -> Vec<(Duration, Vec<u8>)> + Send>;

impl RawDevice {
    pub(crate) fn start(path: &Path, mut handler: Handler) -> RawDevice {
        RawDevice::scripted(
            path,
            Box::new(move |req| vec![(Duration::ZERO, handler(req))]),
        )
    }

    /// A device that writes what `script` says when it says.
    pub(crate) fn scripted(path: &Path, mut script: MbapScript) -> RawDevice {
        let file = open_pty(path);
        let stop = Arc::new(AtomicBool::new(false));
        let seen = Arc::new(Mutex::new(Vec::new()));
        let seen2 = seen.clone();
        let got = Arc::new(Mutex::new(Vec::new()));
        let got2 = got.clone();
        let mut buf = bytes::BytesMut::new();
        let thread = pump(&file, stop.clone(), move |chunk, _, wr| {
            got2.lock().unwrap().extend_from_slice(chunk);
            buf.extend_from_slice(chunk);
            while let Ok(Some(req)) = decode_strict(&mut buf) {
                let read = Instant::now();
                seen2.lock().unwrap().push(req.clone());
                for (after, bytes) in script(&req) {
                    if let Some(wait) = (read + after).checked_duration_since(Instant::now()) {
                        thread::sleep(wait);
                    }
                    if !bytes.is_empty() && write_all_nb(wr, &bytes).is_err() {
                        return false;
                    }
                }
            }
            true
        });
        RawDevice {
            stop,
            file,
            seen,
            got,
            thread: Some(thread),
        }
    }

    /// Writes bytes on the line by itself (a notification, noise).
    pub(crate) fn inject(&mut self, bytes: &[u8]) {
        write_all_nb(&mut self.file, bytes).expect("inject");
    }

    pub(crate) fn requests(&self) -> Vec<Adu> {
        self.seen.lock().unwrap().clone()
    }

    /// Every byte the line brought so far, requests or not.
    pub(crate) fn bytes(&self) -> Vec<u8> {
        self.got.lock().unwrap().clone()
    }
}

fn write_all_nb(f: &mut std::fs::File, mut bytes: &[u8]) -> std::io::Result<()> {
    while !bytes.is_empty() {
        match f.write(bytes) {
            Ok(n) => bytes = &bytes[n..],
            Err(e) if e.kind() == ErrorKind::WouldBlock => thread::sleep(Duration::from_millis(1)),
            Err(e) => return Err(e),
        }
    }
    Ok(())
}

impl Drop for RawDevice {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// A register map answering FC 03 and FC 16 for the listed units, like the CIE-M10
/// (docs/protocol.md §3) but with room for many registers; other units get no answer.
pub(crate) fn register_device(units: &[u8], delay: Duration) -> Handler {
    let units = units.to_vec();
    let mut regs = Registers::default();
    Box::new(move |req: &Adu| {
        if !units.contains(&req.unit()) {
            return vec![];
        }
        thread::sleep(delay);
        let reply_pdu = regs.answer(req.unit(), req.pdu(), false);
        Adu::build(req.tid(), req.unit(), &reply_pdu)
            .as_bytes()
            .to_vec()
    })
}

/// The register map of [`register_device`] and [`rtu_register_device`]: register `a`
/// reads as `a` until written.
#[derive(Default)]
pub(crate) struct Registers(std::collections::HashMap<(u8, u16), u16>);

impl Registers {
    /// The reply PDU to a request PDU: FC 03 and 16, and FC 06 when `single` is set;
    /// exception 01 for anything else.
    pub(crate) fn answer(&mut self, unit: u8, p: &[u8], single: bool) -> Vec<u8> {
        let word = |i: usize| u16::from_be_bytes([p[i], p[i + 1]]);
        match p[0] {
            0x03 => {
                let (addr, qty) = (word(1), word(3));
                let mut v = vec![0x03, (qty * 2) as u8];
                for a in addr..addr + qty {
                    let val = self.0.get(&(unit, a)).copied().unwrap_or(a);
                    v.extend_from_slice(&val.to_be_bytes());
                }
                v
            }
            0x06 if single => {
                self.0.insert((unit, word(1)), word(3));
                p.to_vec()
            }
            0x10 => {
                let (addr, qty) = (word(1), word(3));
                for i in 0..qty {
                    self.0.insert((unit, addr + i), word(6 + 2 * i as usize));
                }
                p[..5].to_vec()
            }
            f => vec![f | 0x80, 0x01],
        }
    }
}

// ---------------------------------------------------------------------------------
// A raw TCP master

/// Reads one MBAP frame (header, then as many bytes as its length says).
pub(crate) fn read_frame(s: &mut TcpStream) -> Vec<u8> {
    try_read_frame(s).expect("read an MBAP frame")
}

/// [`read_frame`], or `None` when the stream ends or its read timeout passes first.
pub(crate) fn try_read_frame(s: &mut TcpStream) -> Option<Vec<u8>> {
    let mut head = [0u8; 6];
    s.read_exact(&mut head).ok()?;
    let len = u16::from_be_bytes([head[4], head[5]]) as usize;
    let mut rest = vec![0u8; len];
    s.read_exact(&mut rest).ok()?;
    Some([head.to_vec(), rest].concat())
}

/// Bytes as docs/protocol.md writes them: `00 01 FF`.
pub(crate) fn hexs(b: &[u8]) -> String {
    mbgate::frame::hex::Hex(b).to_string()
}

/// Sends a request and reads one frame back.
pub(crate) fn transact(s: &mut TcpStream, req: &[u8]) -> Vec<u8> {
    s.write_all(req).expect("send request");
    read_frame(s)
}

/// FC 03 read of `qty` registers at `addr`.
pub(crate) fn read_req(tid: u16, unit: u8, addr: u16, qty: u16) -> Vec<u8> {
    let mut pdu = vec![0x03];
    pdu.extend_from_slice(&addr.to_be_bytes());
    pdu.extend_from_slice(&qty.to_be_bytes());
    Adu::build(tid, unit, &pdu).as_bytes().to_vec()
}

/// FC 16 write of `values` at `addr`.
pub(crate) fn write_req(tid: u16, unit: u8, addr: u16, values: &[u16]) -> Vec<u8> {
    let mut pdu = vec![0x10];
    pdu.extend_from_slice(&addr.to_be_bytes());
    pdu.extend_from_slice(&(values.len() as u16).to_be_bytes());
    pdu.push((values.len() * 2) as u8);
    for v in values {
        pdu.extend_from_slice(&v.to_be_bytes());
    }
    Adu::build(tid, unit, &pdu).as_bytes().to_vec()
}

/// The reply a register read should get.
pub(crate) fn read_reply(tid: u16, unit: u8, values: &[u16]) -> Vec<u8> {
    let mut pdu = vec![0x03, (values.len() * 2) as u8];
    for v in values {
        pdu.extend_from_slice(&v.to_be_bytes());
    }
    Adu::build(tid, unit, &pdu).as_bytes().to_vec()
}

/// Sets a SOL_SOCKET option to `value`, which must be of the type the option takes.
pub(crate) fn set_option<T>(s: &TcpStream, name: libc::c_int, value: &T) {
    // SAFETY: a valid socket, and a pointer to a `T` with its size.
    let r = unsafe {
        libc::setsockopt(
            s.as_raw_fd(),
            libc::SOL_SOCKET,
            name,
            (value as *const T).cast(),
            std::mem::size_of::<T>() as libc::socklen_t,
        )
    };
    assert_eq!(
        r,
        0,
        "setsockopt {name}: {}",
        std::io::Error::last_os_error()
    );
}

/// Closes with SO_LINGER 0: the kernel sends RST instead of FIN and drops what is
/// unsent.
pub(crate) fn reset(s: TcpStream) {
    let linger = libc::linger {
        l_onoff: 1,
        l_linger: 0,
    };
    set_option(&s, libc::SO_LINGER, &linger);
    drop(s);
}

/// Has the gateway closed this connection (EOF or reset) within `within`?
pub(crate) fn is_closed(s: &mut TcpStream, within: Duration) -> bool {
    s.set_read_timeout(Some(within)).unwrap();
    let mut b = [0u8; 1];
    match s.read(&mut b) {
        Ok(0) => true,
        Ok(_) => false,
        Err(e) => matches!(
            e.kind(),
            ErrorKind::ConnectionReset | ErrorKind::ConnectionAborted | ErrorKind::BrokenPipe
        ),
    }
}

/// Time on a CPU of all of a process's threads, in ns (/proc/PID/task/*/schedstat).
pub(crate) fn cpu_ns(pid: u32) -> u64 {
    std::fs::read_dir(format!("/proc/{pid}/task"))
        .expect("tasks")
        .filter_map(|t| std::fs::read_to_string(t.ok()?.path().join("schedstat")).ok())
        .filter_map(|s| s.split_whitespace().next()?.parse::<u64>().ok())
        .sum()
}

#[derive(Debug, Clone, Copy)]
pub(crate) struct Mem {
    pub(crate) rss_kib: u64,
    pub(crate) hwm_kib: u64,
}

/// VmRSS and VmHWM of the gateway; fails the test if the process has exited.
pub(crate) fn mem(gw: &Gateway) -> Mem {
    let pid = gw.proc.pid();
    let status = std::fs::read_to_string(format!("/proc/{pid}/status"))
        .unwrap_or_else(|e| panic!("the gateway is gone ({e}):\n{}", gw.log()));
    let field = |name: &str| -> String {
        status
            .lines()
            .find_map(|l| l.strip_prefix(name))
            .unwrap_or_else(|| panic!("no {name} in /proc/{pid}/status"))
            .trim()
            .to_string()
    };
    assert!(
        !field("State:").starts_with('Z'),
        "the gateway exited:\n{}",
        gw.log()
    );
    let kib = |name: &str| -> u64 {
        let v = field(name);
        v.trim_end_matches("kB")
            .trim()
            .parse()
            .expect("a size in kB")
    };
    Mem {
        rss_kib: kib("VmRSS:"),
        hwm_kib: kib("VmHWM:"),
    }
}

// ---------------------------------------------------------------------------------
// A raw RTU device on the pty, scripted by the test

/// What the raw RTU device does with each request frame (address to CRC, as received).
pub(crate) type RtuHandler = Box<dyn FnMut(&[u8]) -> Vec<u8> + Send>;

/// What a scripted RTU device writes for each request frame: pieces of bytes, each
/// written that long after the request's first byte was read (in order).
pub(crate) type RtuScript = Box<dyn FnMut(&[u8]) -> Vec<(Duration, Vec<u8>)> + Send>;

/// How long `bytes` take on a line at `baud`, 10 bits a byte (8N1).
pub(crate) fn wire_time(bytes: usize, baud: u32) -> Duration {
    Duration::from_micros(bytes as u64 * 10_000_000 / u64::from(baud))
}

/// A device on the `dev` end of a socat pair that reads RTU frames (cut at the length
/// their function code calls for, or after 20 ms of silence), records each exactly as
/// it came, and writes whatever the handler returns (nothing = no answer).
pub(crate) struct RawRtuDevice {
    stop: Arc<AtomicBool>,
    pub(crate) seen: Arc<Mutex<Vec<Vec<u8>>>>,
    /// When each request's first byte was read, in step with `seen`.
    pub(crate) seen_at: Arc<Mutex<Vec<Instant>>>,
    thread: Option<JoinHandle<()>>,
}

impl RawRtuDevice {
    /// A device on a 19 200 baud line (the gateway's default): as a real one, it
    /// answers once the request can have reached it whole, its wire time after its
    /// first byte (a pty delivers it at once).
    pub(crate) fn start(path: &Path, handler: RtuHandler) -> RawRtuDevice {
        RawRtuDevice::start_at(path, 19_200, handler)
    }

    /// [`RawRtuDevice::start`] on a line at `baud`.
    pub(crate) fn start_at(path: &Path, baud: u32, mut handler: RtuHandler) -> RawRtuDevice {
        RawRtuDevice::scripted(
            path,
            Box::new(move |frame: &[u8]| vec![(wire_time(frame.len(), baud), handler(frame))]),
        )
    }

    /// A device that writes what `script` says when it says, early or late.
    pub(crate) fn scripted(path: &Path, mut script: RtuScript) -> RawRtuDevice {
        use mbgate::frame::rtu::{request_length, Length};
        let file = open_pty(path);
        let stop = Arc::new(AtomicBool::new(false));
        let seen = Arc::new(Mutex::new(Vec::new()));
        let seen_at = Arc::new(Mutex::new(Vec::new()));
        let (seen2, seen_at2) = (seen.clone(), seen_at.clone());
        let mut buf: Vec<u8> = Vec::new();
        let mut first_at = Instant::now();
        let thread = pump(&file, stop.clone(), move |chunk, idle, wr| {
            if buf.is_empty() && !chunk.is_empty() {
                first_at = Instant::now();
            }
            buf.extend_from_slice(chunk);
            loop {
                let quiet = idle >= Duration::from_millis(20);
                let n = match request_length(&buf) {
                    Length::Exactly(n) if buf.len() >= n => n,
                    _ if quiet && !buf.is_empty() => buf.len(),
                    _ => return true,
                };
                let frame: Vec<u8> = buf.drain(..n).collect();
                seen2.lock().unwrap().push(frame.clone());
                seen_at2.lock().unwrap().push(first_at);
                for (after, bytes) in script(&frame) {
                    if let Some(wait) = (first_at + after).checked_duration_since(Instant::now()) {
                        thread::sleep(wait);
                    }
                    if !bytes.is_empty() && write_all_nb(wr, &bytes).is_err() {
                        return false;
                    }
                }
            }
        });
        RawRtuDevice {
            stop,
            seen,
            seen_at,
            thread: Some(thread),
        }
    }

    pub(crate) fn requests(&self) -> Vec<Vec<u8>> {
        self.seen.lock().unwrap().clone()
    }
}

impl Drop for RawRtuDevice {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// A register map like [`register_device`], for RTU: FC 03 reads register `a` as `a`
/// (or what was written), FC 06 and 16 write; units not listed get no answer; a
/// frame whose CRC is wrong gets none either, as on a bus.
pub(crate) fn rtu_register_device(units: &[u8]) -> RtuHandler {
    use mbgate::frame::rtu;
    let units = units.to_vec();
    let mut regs = Registers::default();
    Box::new(move |frame: &[u8]| match rtu::decode(frame) {
        Some((unit, p)) if units.contains(&unit) => rtu::encode(unit, &regs.answer(unit, p, true)),
        _ => vec![],
    })
}

/// `mbpoll -m tcp -p PORT -a UNIT -0 -1 -o 3 ARGS 127.0.0.1 VALUES`, run to its end.
pub(crate) fn mbpoll_run(
    port: u16,
    unit: u8,
    args: &[&str],
    values: &[&str],
) -> std::process::Output {
    Command::new("mbpoll")
        .args([
            "-m",
            "tcp",
            "-p",
            &port.to_string(),
            "-a",
            &unit.to_string(),
        ])
        .args(["-0", "-1", "-o", "3"])
        .args(args)
        .arg("127.0.0.1")
        .args(values)
        .output()
        .expect("mbpoll (apt-get install mbpoll; scripts/test does)")
}
