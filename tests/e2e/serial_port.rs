//! The serial side on a real pty: the `[serial]` settings reach the port's termios, and
//! stale bytes are cleared on open (docs/design.md §4 `[serial]`).

use crate::common;
use common::*;
use mbgate::config::{FlowControl, Parity, SerialConfig};
use std::io::Write;
use std::os::fd::AsRawFd;

fn termios(fd: i32) -> libc::termios {
    let mut t: libc::termios = unsafe { std::mem::zeroed() };
    assert_eq!(unsafe { libc::tcgetattr(fd, &mut t) }, 0);
    t
}

/// The line speed as Linux keeps it: serialport sets it with termios2 and BOTHER, so
/// the classic `cfgetospeed` only says "other".
fn speed(fd: i32) -> u32 {
    let mut t: libc::termios2 = unsafe { std::mem::zeroed() };
    assert_eq!(unsafe { libc::ioctl(fd, libc::TCGETS2, &mut t) }, 0);
    t.c_ospeed
}

fn bytes_waiting(fd: i32) -> i32 {
    let mut n: libc::c_int = 0;
    assert_eq!(unsafe { libc::ioctl(fd, libc::FIONREAD, &mut n) }, 0);
    n
}

/// tokio-serial registers the port with a reactor: open it inside a runtime.
fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
}

#[test]
fn settings_reach_termios() {
    let rt = runtime();
    let _guard = rt.enter();
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let cases = [
        (19200, 8, Parity::None, 1, FlowControl::Hardware),
        (9600, 7, Parity::Even, 2, FlowControl::Software),
        (115200, 8, Parity::Odd, 1, FlowControl::None),
    ];
    for (baud, data_bits, parity, stop_bits, flow) in cases {
        let cfg = SerialConfig {
            path: socat.gw.display().to_string(),
            baud_rate: baud,
            data_bits,
            parity,
            stop_bits,
            flow_control: flow,
            ..SerialConfig::default()
        };
        let port = mbgate::line::port::serial::open(&cfg).expect("open pty");
        let t = termios(port.as_raw_fd());
        let what = format!("{baud} {data_bits} {parity:?} {stop_bits} {flow:?}");
        assert_eq!(speed(port.as_raw_fd()), baud, "{what}");
        // Data bits and parity cannot be seen here: the pty driver forces CS8 and
        // clears PARENB on every change (pty_set_termios). `port::serial` `line_settings` is
        // unit-tested for them instead.
        assert_eq!(t.c_cflag & libc::CSTOPB != 0, stop_bits == 2, "{what}");
        assert_eq!(
            t.c_cflag & libc::CRTSCTS != 0,
            flow == FlowControl::Hardware,
            "{what}"
        );
        assert_eq!(
            t.c_iflag & libc::IXON != 0,
            flow == FlowControl::Software,
            "{what}"
        );
        // Raw: no echo, no line editing, no CR/NL mangling of binary frames.
        assert_eq!(
            t.c_lflag & (libc::ICANON | libc::ECHO | libc::ISIG),
            0,
            "{what}"
        );
        assert_eq!(t.c_iflag & (libc::ICRNL | libc::INLCR), 0, "{what}");
        assert_eq!(t.c_oflag & libc::OPOST, 0, "{what}");
    }
}

#[test]
fn stale_bytes_are_cleared_on_open() {
    let rt = runtime();
    let _guard = rt.enter();
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let cfg = SerialConfig {
        path: socat.gw.display().to_string(),
        ..SerialConfig::default()
    };
    // Open once so the pty is configured raw, then leave bytes waiting on it.
    let first = mbgate::line::port::serial::open(&cfg).expect("open pty");
    let mut dev = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&socat.dev)
        .unwrap();
    dev.write_all(&hex("00 05 00 00 00 06 01 03 DE AD"))
        .unwrap();
    let start = std::time::Instant::now();
    while bytes_waiting(first.as_raw_fd()) < 10 {
        assert!(start.elapsed().as_secs() < 5, "stale bytes never arrived");
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    drop(first);
    let port = mbgate::line::port::serial::open(&cfg).expect("reopen pty");
    assert_eq!(
        bytes_waiting(port.as_raw_fd()),
        0,
        "stale bytes survived the open"
    );
}
