//! Peers for the simulator's tests: an `mbgate` child process whose log is captured
//! (`mbgate sim`, `mbgate demo`), and a raw master on a pty.

use std::io::{BufRead, BufReader, ErrorKind, Read, Write};
use std::os::unix::fs::OpenOptionsExt;
use std::path::Path;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::{Arc, Mutex};
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

/// An `mbgate` subcommand running as a child, stderr captured as its log.
pub struct Proc {
    child: Child,
    log: Arc<Mutex<String>>,
    reader: Option<JoinHandle<()>>,
    pub stdout: Arc<Mutex<String>>,
}

impl Proc {
    /// Starts `mbgate ARGS` and waits until its log shows `ready`.
    pub fn start(args: &[&str], ready: &str) -> Proc {
        let mut child = Command::new(env!("CARGO_BIN_EXE_mbgate"))
            .args(args)
            .env_remove("RUST_LOG")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start mbgate");
        let log = Arc::new(Mutex::new(String::new()));
        let stdout = Arc::new(Mutex::new(String::new()));
        let (err, out) = (child.stderr.take().unwrap(), child.stdout.take().unwrap());
        let sink = log.clone();
        let reader = thread::spawn(move || {
            for line in BufReader::new(err).lines() {
                let Ok(line) = line else { break };
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
            reader: Some(reader),
            stdout,
        };
        p.wait_log(ready, Duration::from_secs(10));
        p
    }

    pub fn log(&self) -> String {
        self.log.lock().unwrap().clone()
    }

    pub fn wait_log(&self, needle: &str, timeout: Duration) {
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

    /// SIGTERM, then waits (bounded) for the exit.
    pub fn terminate(&mut self, within: Duration) -> ExitStatus {
        let _ = Command::new("kill")
            .arg("-TERM")
            .arg(self.child.id().to_string())
            .status();
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

/// `mbgate sim --serial PATH ARGS`, started once it has the port open.
pub fn sim(path: &Path, args: &[&str]) -> Proc {
    let path = path.to_str().unwrap();
    let all: Vec<&str> = ["sim", "--serial", path]
        .iter()
        .chain(args)
        .copied()
        .collect();
    Proc::start(&all, "simulating ")
}

/// A master that writes and reads raw bytes on a pty (the gateway's end of a socat
/// pair), to talk to the simulator directly.
pub struct RawLine {
    file: std::fs::File,
}

impl RawLine {
    pub fn open(path: &Path) -> RawLine {
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags(libc::O_NONBLOCK | libc::O_NOCTTY)
            .open(path)
            .expect("open pty");
        RawLine { file }
    }

    pub fn send(&mut self, mut bytes: &[u8]) {
        while !bytes.is_empty() {
            match self.file.write(bytes) {
                Ok(n) => bytes = &bytes[n..],
                Err(e) if e.kind() == ErrorKind::WouldBlock => {
                    thread::sleep(Duration::from_millis(1))
                }
                Err(e) => panic!("write to pty: {e}"),
            }
        }
    }

    /// Reads until `n` bytes have come or `timeout` has passed.
    pub fn recv(&mut self, n: usize, timeout: Duration) -> Vec<u8> {
        self.recv_while(timeout, None, |got| got.len() < n)
    }

    /// Reads until the line has been quiet for `quiet` (or `limit` has passed).
    pub fn recv_until_quiet(&mut self, quiet: Duration, limit: Duration) -> Vec<u8> {
        self.recv_while(limit, Some(quiet), |_| true)
    }

    fn recv_while(
        &mut self,
        limit: Duration,
        quiet: Option<Duration>,
        more: impl Fn(&[u8]) -> bool,
    ) -> Vec<u8> {
        let start = Instant::now();
        let mut last = Instant::now();
        let mut got = Vec::new();
        let mut chunk = [0u8; 4096];
        while more(&got) && start.elapsed() < limit {
            match self.file.read(&mut chunk) {
                Ok(0) => break,
                Ok(k) => {
                    got.extend_from_slice(&chunk[..k]);
                    last = Instant::now();
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock => {
                    if quiet.is_some_and(|q| last.elapsed() >= q) {
                        break;
                    }
                    thread::sleep(Duration::from_millis(1));
                }
                Err(e) => panic!("read from pty: {e}"),
            }
        }
        got
    }

    /// Sends a request and reads one reply of the expected size.
    pub fn transact(&mut self, request: &[u8], reply_len: usize) -> Vec<u8> {
        self.send(request);
        self.recv(reply_len, Duration::from_secs(5))
    }
}
