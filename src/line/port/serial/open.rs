//! Opening the serial port (docs/design.md §4 `[serial]`).
//!
//! Baud, data bits, parity, stop bits and flow control come from the configuration;
//! RTS/CTS is the default because the CIE-M10 manual asks for it (docs/protocol.md §3). A
//! freshly opened port can hold stale bytes, so it is flushed before use. Opened
//! exclusively; "busy" names who holds it. RS-485 mode when asked. Modem-line calls
//! fail with ENOTTY on a pty; nothing here treats that as fatal.

use crate::config::{FlowControl, Parity, SerialConfig};
use serialport::TTYPort;
use std::os::fd::{AsRawFd, RawFd};
use std::sync::atomic::{AtomicBool, Ordering};
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
/// users are invisible without privilege, so an empty list proves nothing. On a pty
/// (`/dev/pts/N`), a process that also holds its master (a `ptmx` descriptor whose
/// `fdinfo` says `tty-index: N`) is the line's far side (socat, `mbgate wire`), which
/// keeps the device open so that its settings stay between programs: not a holder.
pub(crate) fn holders(path: &str) -> Vec<String> {
    let Ok(target) = std::fs::canonicalize(path) else {
        return Vec::new();
    };
    let pty_index = target
        .strip_prefix("/dev/pts")
        .ok()
        .and_then(|n| n.to_str()?.parse::<u32>().ok());
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
        let links: Vec<(std::ffi::OsString, std::path::PathBuf)> = fds
            .flatten()
            .filter_map(|fd| Some((fd.file_name(), std::fs::read_link(fd.path()).ok()?)))
            .collect();
        if !links.iter().any(|(_, l)| *l == target) {
            continue;
        }
        let far_side = pty_index.is_some_and(|n| {
            links.iter().any(|(fd, l)| {
                l.file_name().is_some_and(|f| f == "ptmx")
                    && pty_master_of(&entry.path().join("fdinfo").join(fd)) == Some(n)
            })
        });
        if !far_side {
            let name = std::fs::read_to_string(entry.path().join("comm")).unwrap_or_default();
            found.push(format!("{pid} ({})", name.trim()));
        }
    }
    found
}

/// The pty index a master descriptor serves, from its `/proc/PID/fdinfo/FD`.
fn pty_master_of(fdinfo: &std::path::Path) -> Option<u32> {
    std::fs::read_to_string(fdinfo)
        .ok()?
        .lines()
        .find_map(|l| l.strip_prefix("tty-index:"))?
        .trim()
        .parse()
        .ok()
}

/// Who holds a port, for the user, when someone visible does: ` (held by process 123
/// (minicom))`, else nothing.
pub fn held_by(path: &str) -> String {
    match holders(path).as_slice() {
        [] => String::new(),
        pids => format!(" (held by process {})", pids.join(", ")),
    }
}

/// Opens and configures the port, then clears whatever it held, as a stream on the
/// current runtime's reactor (the simulator, the client, scan).
pub fn open(cfg: &SerialConfig) -> Result<SerialStream, tokio_serial::Error> {
    SerialStream::try_from(open_tty(cfg)?)
}

/// Opens and configures the port, then clears whatever it held: the port itself,
/// blocking, for the gateway's own reader and writer (`stream.rs`).
pub(crate) fn open_tty(cfg: &SerialConfig) -> Result<TTYPort, tokio_serial::Error> {
    let (data_bits, parity, stop_bits, flow_control) = line_settings(cfg);
    let builder = tokio_serial::new(&cfg.path, cfg.baud_rate)
        .data_bits(data_bits)
        .parity(parity)
        .stop_bits(stop_bits)
        .flow_control(flow_control);
    let port = match TTYPort::open(&builder) {
        Ok(port) => port,
        // A kernel or emulator without termios2: the classic calls can still set a
        // standard rate (classic.rs).
        Err(e) if super::classic::termios2_missing(&cfg.path) => {
            tracing::info!(
                path = %cfg.path,
                "no termios2 here ({e}); setting the port with the classic termios calls"
            );
            super::classic::open(cfg).map_err(|e| held_elsewhere(e, &cfg.path))?
        }
        Err(e) => return Err(held_elsewhere(e, &cfg.path)),
    };
    // Opened exclusively from here on; a process that had it open before keeps it,
    // and would read part of every reply (docs/troubleshooting.md).
    let others = holders(&cfg.path);
    if !others.is_empty() {
        return Err(tokio_serial::Error::new(
            tokio_serial::ErrorKind::Io(std::io::ErrorKind::ResourceBusy),
            format!(
                "another process has the port open (held by process {}): two programs \
                 on one port each read part of the other's bytes; stop it first",
                others.join(", ")
            ),
        ));
    }
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

#[cfg(test)]
mod tests {
    use super::*;

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
