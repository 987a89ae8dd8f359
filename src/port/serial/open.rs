//! Opening the serial port (docs/design.md §4 `[serial]`).
//!
//! Baud, data bits, parity, stop bits and flow control come from the configuration;
//! RTS/CTS is the default because the CIE-M10 manual asks for it (docs/protocol.md §3). A
//! freshly opened port can hold stale bytes, so it is flushed before use. Modem-line
//! calls fail with ENOTTY on a pty; nothing here treats that as fatal. Also what the
//! line's timing asks of the OS: the drain thread, FIONREAD, and a timer finer than
//! tokio's millisecond.

use crate::config::{FlowControl, Parity, SerialConfig};
use std::os::fd::{AsRawFd, BorrowedFd, FromRawFd, RawFd};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;
use tokio_serial::{ClearBuffer, SerialPort, SerialStream};

/// The `[serial]` settings in tokio-serial's terms: data bits, parity, stop bits, flow
/// control.
pub(crate) fn line_settings(
    cfg: &SerialConfig,
) -> (
    tokio_serial::DataBits,
    tokio_serial::Parity,
    tokio_serial::StopBits,
    tokio_serial::FlowControl,
) {
    (
        match cfg.data_bits {
            7 => tokio_serial::DataBits::Seven,
            _ => tokio_serial::DataBits::Eight,
        },
        match cfg.parity {
            Parity::None => tokio_serial::Parity::None,
            Parity::Even => tokio_serial::Parity::Even,
            Parity::Odd => tokio_serial::Parity::Odd,
        },
        match cfg.stop_bits {
            2 => tokio_serial::StopBits::Two,
            _ => tokio_serial::StopBits::One,
        },
        match cfg.flow_control {
            FlowControl::Hardware => tokio_serial::FlowControl::Hardware,
            FlowControl::Software => tokio_serial::FlowControl::Software,
            FlowControl::None => tokio_serial::FlowControl::None,
        },
    )
}

/// The processes other than this one that have `path` open, as `PID (name)`, found
/// the way `fuser` finds them: through the links in `/proc/*/fd`. Processes of other
/// users are invisible without privilege, so an empty list proves nothing.
pub(crate) fn holders(path: &str) -> Vec<String> {
    let Ok(target) = std::fs::canonicalize(path) else {
        return Vec::new();
    };
    let me = std::process::id().to_string();
    let Ok(procs) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    let mut found = Vec::new();
    for entry in procs.flatten() {
        let pid = entry.file_name().to_string_lossy().into_owned();
        if pid == me || !pid.bytes().all(|b| b.is_ascii_digit()) {
            continue;
        }
        let Ok(fds) = std::fs::read_dir(entry.path().join("fd")) else {
            continue;
        };
        let holds = fds
            .flatten()
            .any(|fd| std::fs::read_link(fd.path()).is_ok_and(|l| l == target));
        if holds {
            let name = std::fs::read_to_string(entry.path().join("comm")).unwrap_or_default();
            found.push(format!("{pid} ({})", name.trim()));
        }
    }
    found
}

/// Who holds a port, for the user, when someone visible does: ` (held by process 123
/// (minicom))`, else nothing.
pub fn held_by(path: &str) -> String {
    match holders(path).as_slice() {
        [] => String::new(),
        pids => format!(" (held by process {})", pids.join(", ")),
    }
}

/// Opens and configures the port, then clears whatever it held.
pub fn open(cfg: &SerialConfig) -> Result<SerialStream, tokio_serial::Error> {
    let (data_bits, parity, stop_bits, flow_control) = line_settings(cfg);
    let builder = tokio_serial::new(&cfg.path, cfg.baud_rate)
        .data_bits(data_bits)
        .parity(parity)
        .stop_bits(stop_bits)
        .flow_control(flow_control);
    let port = SerialStream::open(&builder).map_err(|e| held_elsewhere(e, &cfg.path))?;
    if let Err(e) = port.clear(ClearBuffer::All) {
        tracing::debug!(path = %cfg.path, "could not clear stale bytes: {e}");
    }
    if cfg.rs485 {
        match set_rs485(port.as_raw_fd(), cfg) {
            Ok(()) => tracing::info!(path = %cfg.path, "RS-485 mode on"),
            // Once: a port that cannot do it cannot after a reopen either.
            Err(e) if !RS485_WARNED.swap(true, Ordering::Relaxed) => tracing::warn!(
                path = %cfg.path,
                "rs485 = true, but the port does not support RS-485 mode ({e}); \
                 using it as it is (an adapter that switches by itself needs nothing more)"
            ),
            Err(e) => tracing::debug!(path = %cfg.path, "RS-485 mode: {e}"),
        }
    }
    Ok(port)
}

static RS485_WARNED: AtomicBool = AtomicBool::new(false);

/// The port is opened exclusively (TIOCEXCL and an exclusive flock), so "busy" means
/// another process has it open: say so, since "Device or resource busy" alone sends
/// the operator looking at the device.
fn held_elsewhere(e: tokio_serial::Error, path: &str) -> tokio_serial::Error {
    if e.kind != tokio_serial::ErrorKind::NoDevice {
        return e;
    }
    let what = format!(
        "{}: another process holds the port{} (a second mbgate for the same port, \
         a terminal program, ModemManager?)",
        e.description,
        held_by(path)
    );
    tokio_serial::Error::new(e.kind, what)
}

/// The kernel's `struct serial_rs485` (linux/serial.h); libc does not define it.
#[repr(C)]
#[derive(Debug, Default)]
struct SerialRs485 {
    flags: u32,
    /// Milliseconds.
    delay_rts_before_send: u32,
    /// Milliseconds.
    delay_rts_after_send: u32,
    padding: [u32; 5],
}

const SER_RS485_ENABLED: u32 = 1 << 0;
const SER_RS485_RTS_ON_SEND: u32 = 1 << 1;

/// Turns on the driver's RS-485 mode (TIOCSRS485): RTS high while sending, low after,
/// with the configured delays. A pty or a plain UART driver refuses (ENOTTY, EINVAL).
fn set_rs485(fd: RawFd, cfg: &SerialConfig) -> std::io::Result<()> {
    let conf = SerialRs485 {
        flags: SER_RS485_ENABLED | SER_RS485_RTS_ON_SEND,
        delay_rts_before_send: cfg.rs485_delay_before_send_ms,
        delay_rts_after_send: cfg.rs485_delay_after_send_ms,
        ..SerialRs485::default()
    };
    // SAFETY: TIOCSRS485 reads one `struct serial_rs485`, which `conf` is, for the
    // duration of the call; `fd` is the open port.
    #[allow(unsafe_code)]
    let r = unsafe { libc::ioctl(fd, libc::TIOCSRS485 as _, &conf as *const SerialRs485) };
    if r == 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}

/// What a drain answers: when `tcdrain` returned, or why it failed.
pub type Drained = std::io::Result<std::time::Instant>;

/// A thread of the port's own that waits, when asked, until everything written to the
/// port has left it (`tcdrain`), so the runtime's thread never blocks on it
/// (docs/performance.md, "RTU at the line's limit"). Made once when the port opens: it
/// owns a duplicate of the descriptor, made then (closing the port meanwhile cannot
/// make it touch another file), and each drain costs one wake of it and one of the
/// runtime, with no descriptor made and closed and no trip through tokio's blocking
/// pool. It ends, closing its duplicate, when the [`Drainer`] is dropped and the drain
/// it may be in has returned.
#[derive(Debug)]
pub struct Drainer {
    asks: std::sync::mpsc::Sender<tokio::sync::oneshot::Sender<Drained>>,
}

impl Drainer {
    /// Starts the thread for the open port `fd`.
    pub fn start(fd: RawFd) -> std::io::Result<Drainer> {
        // SAFETY: `fd` is the open port, borrowed only to duplicate it.
        #[allow(unsafe_code)]
        let owned = unsafe { BorrowedFd::borrow_raw(fd) }.try_clone_to_owned()?;
        let (asks, asked) = std::sync::mpsc::channel::<tokio::sync::oneshot::Sender<Drained>>();
        std::thread::Builder::new()
            .name("mbgate-drain".into())
            .spawn(move || {
                for answer in asked {
                    // SAFETY: a valid descriptor, ours until `owned` drops when the
                    // thread ends.
                    #[allow(unsafe_code)]
                    let r = unsafe { libc::tcdrain(owned.as_raw_fd()) };
                    // Dated here, not where the relay learns it: its thread may be
                    // scheduled late, and the gap counts from the last byte out.
                    let at = std::time::Instant::now();
                    let _ = answer.send(if r == 0 {
                        Ok(at)
                    } else {
                        Err(std::io::Error::last_os_error())
                    });
                }
            })?;
        Ok(Drainer { asks })
    }

    /// Asks for a drain of everything written so far; the answer comes on the
    /// receiver. An error says the thread is gone.
    pub fn drain(&self) -> std::io::Result<tokio::sync::oneshot::Receiver<Drained>> {
        let (answer, answered) = tokio::sync::oneshot::channel();
        self.asks
            .send(answer)
            .map_err(|_| std::io::Error::other("the drain thread is gone"))?;
        Ok(answered)
    }
}

/// A timer as precise as the kernel's (a timerfd on tokio's reactor): tokio's own
/// counts whole milliseconds and rounds a deadline up, which turns the 1750 µs gap
/// before an RTU request into 2 to 3 ms (docs/performance.md, "RTU at the line's
/// limit"). No thread and no spinning: the timerfd wakes the reactor's `epoll_wait`
/// at the instant it is set to.
#[derive(Debug)]
pub struct PreciseTimer {
    fd: tokio::io::unix::AsyncFd<std::os::fd::OwnedFd>,
    /// The instant it is set to go off.
    armed: Option<tokio::time::Instant>,
}

impl PreciseTimer {
    /// A timer on the current runtime's reactor; an error where there is no timerfd.
    pub fn new() -> std::io::Result<PreciseTimer> {
        // SAFETY: no pointers; the descriptor returned is checked and then owned.
        #[allow(unsafe_code)]
        let fd = unsafe {
            libc::timerfd_create(
                libc::CLOCK_MONOTONIC,
                libc::TFD_NONBLOCK | libc::TFD_CLOEXEC,
            )
        };
        if fd < 0 {
            return Err(std::io::Error::last_os_error());
        }
        // SAFETY: `fd` was just made, is valid and belongs to nothing else.
        #[allow(unsafe_code)]
        let owned = unsafe { std::os::fd::OwnedFd::from_raw_fd(fd) };
        // SAFETY: an `OwnedFd` keeps its descriptor open, and the same, until it drops,
        // which is when the `AsyncFd` holding it does.
        #[allow(unsafe_code)]
        let fd = unsafe {
            tokio::io::unix::AsyncFd::register_with_interest(owned, tokio::io::Interest::READABLE)
        }?;
        Ok(PreciseTimer { fd, armed: None })
    }

    /// Returns at `at`, or at once if it has passed. Sets the timerfd only when `at` is
    /// not what it is already set to: a loop that waits for the same instant several
    /// times makes one system call for it.
    pub async fn until(&mut self, at: tokio::time::Instant) -> std::io::Result<()> {
        let now = tokio::time::Instant::now();
        if at <= now {
            return Ok(());
        }
        if self.armed != Some(at) {
            // Relative to a `now` read before the call: the kernel's clock has moved on
            // since, so it goes off at `at` or after, never before. (Setting it also
            // zeroes its count of expirations, so it is never read.)
            let rest = at - now;
            let spec = libc::itimerspec {
                it_interval: libc::timespec {
                    tv_sec: 0,
                    tv_nsec: 0,
                },
                it_value: libc::timespec {
                    tv_sec: rest.as_secs() as libc::time_t,
                    tv_nsec: libc::c_long::from(rest.subsec_nanos() as i32),
                },
            };
            // SAFETY: `spec` is a valid itimerspec for the duration of the call; the old
            // value is not asked for (null).
            #[allow(unsafe_code)]
            let r = unsafe {
                libc::timerfd_settime(self.fd.as_raw_fd(), 0, &spec, std::ptr::null_mut())
            };
            if r != 0 {
                return Err(std::io::Error::last_os_error());
            }
            self.armed = Some(at);
        }
        loop {
            let mut ready = self.fd.readable().await?;
            // Readiness left over from an earlier setting says nothing about this one:
            // each expiry wakes the reactor anew (edge-triggered), so clearing it and
            // waiting again loses nothing.
            ready.clear_ready();
            if tokio::time::Instant::now() >= at {
                return Ok(());
            }
        }
    }
}

/// Bytes received by the port `fd` and not yet read (FIONREAD).
pub(crate) fn input_waiting(fd: RawFd) -> std::io::Result<usize> {
    let mut n: libc::c_int = 0;
    // SAFETY: FIONREAD writes one int, which `n` is, for the duration of the call.
    #[allow(unsafe_code)]
    let r = unsafe { libc::ioctl(fd, libc::FIONREAD as _, &mut n as *mut libc::c_int) };
    if r == 0 {
        Ok(usize::try_from(n).unwrap_or(0))
    } else {
        Err(std::io::Error::last_os_error())
    }
}

/// Bits on the wire for one character: start, data, parity, stop.
pub(crate) fn bits_per_char(cfg: &SerialConfig) -> u32 {
    1 + u32::from(cfg.data_bits) + u32::from(cfg.parity != Parity::None) + u32::from(cfg.stop_bits)
}

/// How long `bytes` take on the wire at the configured rate.
pub(crate) fn wire_time(cfg: &SerialConfig, bytes: usize) -> Duration {
    let bits = bytes as u64 * u64::from(bits_per_char(cfg));
    Duration::from_micros(bits * 1_000_000 / u64::from(cfg.baud_rate.max(1)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::port::Backoff;

    #[test]
    fn backoff_doubles_up_to_max_and_resets() {
        let mut b = Backoff::new(Duration::from_millis(100), Duration::from_millis(500));
        let got: Vec<u64> = (0..5).map(|_| b.next_delay().as_millis() as u64).collect();
        assert_eq!(got, [100, 200, 400, 500, 500]);
        b.reset();
        assert_eq!(b.next_delay(), Duration::from_millis(100));
    }

    /// The timer goes off at its instant, not before and not a millisecond after (the
    /// bound is loose for a loaded machine; tokio's timer alone would take the 1750 µs
    /// to 2 or 3 ms, and the median of these is checked against 700 µs); an expiry
    /// nobody waited for does not end a later wait early.
    #[tokio::test]
    async fn precise_timer_is_neither_early_nor_a_tick_late() {
        use tokio::time::Instant;
        let mut timer = PreciseTimer::new().unwrap();
        let mut late = Vec::new();
        for _ in 0..20 {
            let at = Instant::now() + Duration::from_micros(1750);
            timer.until(at).await.unwrap();
            let now = Instant::now();
            assert!(now >= at, "{:?} early", at - now);
            late.push(now - at);
        }
        late.sort();
        assert!(
            late[10] < Duration::from_micros(700),
            "median {:?} late",
            late[10]
        );

        // Set for 1 ms and dropped unwaited: it goes off while the reactor waits for
        // something else; a later, longer wait must not end with that expiry.
        let first = Instant::now() + Duration::from_millis(1);
        let _ = tokio::time::timeout(Duration::ZERO, timer.until(first)).await;
        tokio::time::sleep(Duration::from_millis(4)).await;
        let second = Instant::now() + Duration::from_millis(5);
        timer.until(second).await.unwrap();
        assert!(Instant::now() >= second, "woken by the earlier expiry");
        // An instant already past returns at once.
        timer.until(first).await.unwrap();
    }

    #[test]
    fn wire_time_at_19200_8n1() {
        let cfg = SerialConfig::default();
        assert_eq!(bits_per_char(&cfg), 10);
        // 12 bytes x 10 bits / 19200 bit/s = 6.25 ms
        assert_eq!(wire_time(&cfg, 12), Duration::from_micros(6250));
    }

    #[test]
    fn line_settings_follow_the_config() {
        use tokio_serial::{DataBits, FlowControl as F, Parity as P, StopBits};
        let cfg = SerialConfig {
            data_bits: 7,
            parity: Parity::Even,
            stop_bits: 2,
            flow_control: FlowControl::Software,
            ..SerialConfig::default()
        };
        assert_eq!(
            line_settings(&cfg),
            (DataBits::Seven, P::Even, StopBits::Two, F::Software)
        );
        let cfg = SerialConfig {
            parity: Parity::Odd,
            ..SerialConfig::default()
        };
        assert_eq!(
            line_settings(&cfg),
            (DataBits::Eight, P::Odd, StopBits::One, F::Hardware)
        );
        assert_eq!(
            line_settings(&SerialConfig::default()).1,
            P::None,
            "8N1 with RTS/CTS by default"
        );
    }

    #[test]
    fn a_missing_port_is_an_error_not_a_panic() {
        let cfg = SerialConfig {
            path: "/nonexistent/ttyUSB9".into(),
            ..SerialConfig::default()
        };
        assert!(open(&cfg).is_err());
    }

    #[test]
    fn holders_names_the_process_that_has_the_port_open() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ttyFAKE");
        std::fs::write(&path, b"").unwrap();
        let path = path.to_str().unwrap().to_string();
        assert_eq!(held_by(&path), "", "nobody holds it yet");
        let mut sleeper = std::process::Command::new("sleep")
            .arg("30")
            .stdin(std::fs::File::open(&path).unwrap())
            .spawn()
            .unwrap();
        let pid = sleeper.id();
        let held = held_by(&path);
        sleeper.kill().unwrap();
        sleeper.wait().unwrap();
        assert_eq!(held, format!(" (held by process {pid} (sleep))"));
    }
}
