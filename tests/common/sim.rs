//! Peers for the simulator's tests: `mbgate sim` as a child, and a raw master on a pty.

use super::Proc;
use std::io::{ErrorKind, Read, Write};
use std::os::unix::io::AsRawFd;
use std::path::Path;
use std::thread;
use std::time::{Duration, Instant};

/// `mbgate sim --serial PATH ARGS`, started once it has the port open.
pub(crate) fn sim(path: &Path, args: &[&str]) -> Proc {
    let path = path.to_str().unwrap();
    let all: Vec<&str> = ["sim", "--serial", path]
        .iter()
        .chain(args)
        .copied()
        .collect();
    Proc::start(&all, "simulating ")
}

/// `mbgate sim` as generic devices with the given unit ids (`"1,2"`) on an RTU or
/// ASCII line paced at 19 200 baud, each holding register holding its address.
pub(crate) fn serial_units(path: &Path, framing: &str, units: &str) -> Proc {
    sim(path, &generic_flags(framing, units, "19200"))
}

/// The flags of [`serial_units`]: generic devices with these unit ids, in `framing`,
/// paced at `baud`, each holding register holding its address, no console.
pub(crate) fn generic_flags<'a>(framing: &'a str, units: &'a str, baud: &'a str) -> Vec<&'a str> {
    vec![
        "--framing",
        framing,
        "--profile",
        "generic",
        "--units",
        units,
        "--fill",
        "address",
        "--baud",
        baud,
        "--headless",
    ]
}

/// A master that writes and reads raw bytes on a pty (the gateway's end of a socat
/// pair), to talk to the simulator directly.
pub(crate) struct RawLine {
    file: std::fs::File,
}

impl RawLine {
    pub(crate) fn open(path: &Path) -> RawLine {
        RawLine {
            file: super::open_pty(path),
        }
    }

    pub(crate) fn send(&mut self, mut bytes: &[u8]) {
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
    pub(crate) fn recv(&mut self, n: usize, timeout: Duration) -> Vec<u8> {
        self.recv_while(timeout, None, |got| got.len() < n)
    }

    /// Reads until the line has been quiet for `quiet` (or `limit` has passed).
    pub(crate) fn recv_until_quiet(&mut self, quiet: Duration, limit: Duration) -> Vec<u8> {
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
                    let mut wait = limit.saturating_sub(start.elapsed());
                    if let Some(q) = quiet {
                        if last.elapsed() >= q {
                            break;
                        }
                        wait = wait.min(q - last.elapsed());
                    }
                    self.wait_readable(wait);
                }
                Err(e) => panic!("read from pty: {e}"),
            }
        }
        got
    }

    /// Blocks until the pty has bytes to read or `wait` has passed, so a reply is
    /// seen as soon as it comes (the benchmarks time replies with this).
    fn wait_readable(&self, wait: Duration) {
        let mut fd = libc::pollfd {
            fd: self.file.as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        };
        let ms = wait.as_millis().clamp(1, i32::MAX as u128) as i32;
        // SAFETY: one valid pollfd for the duration of the call.
        unsafe { libc::poll(&mut fd, 1, ms) };
    }

    /// Sends a request and reads one reply of the expected size.
    pub(crate) fn transact(&mut self, request: &[u8], reply_len: usize) -> Vec<u8> {
        self.send(request);
        self.recv(reply_len, Duration::from_secs(5))
    }
}
