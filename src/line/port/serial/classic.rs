//! Opening a port with the classic termios calls (TCGETS/TCSETS, a `Bnnn` speed) where
//! termios2 is missing.
//!
//! The serial crate reads and sets every port with TCGETS2/TCSETS2 (termios2, any baud
//! rate as a number). A kernel before 2.6.20 has no termios2, and QEMU's user-mode
//! emulator up to 10.0 does not translate it (it answers ENOTTY or ENOSYS while TCGETS
//! works), which is where the static ARM binaries are checked (docs/install.md). There
//! the port is opened here instead, with the same settings as the crate would set (raw,
//! CREAD and CLOCAL, data bits, parity, stop bits, flow control), limited to the
//! standard rates the `Bnnn` constants name. Used only after the crate's open failed
//! and [`termios2_missing`] says why, so a normal kernel never takes this path.

use crate::config::{FlowControl, Parity, SerialConfig};
use std::fs::{File, OpenOptions};
use std::io;
use std::os::fd::{AsRawFd, FromRawFd, IntoRawFd, RawFd};
use std::os::unix::fs::OpenOptionsExt;
use tokio_serial::ErrorKind;

/// Whether `path` is a terminal that refuses TCGETS2 (ENOTTY, ENOSYS or EINVAL) while
/// it answers TCGETS: the one failure of the crate's open this module can mend.
pub(crate) fn termios2_missing(path: &str) -> bool {
    let Ok(file) = open_nonblocking(path) else {
        return false;
    };
    let fd = file.as_raw_fd();
    let Err(e) = get2(fd) else {
        return false;
    };
    let refused = matches!(
        e.raw_os_error(),
        Some(libc::ENOTTY | libc::ENOSYS | libc::EINVAL)
    );
    refused && get(fd).is_ok()
}

/// The `Bnnn` constant of a standard rate, if `baud` is one.
pub(crate) fn speed(baud: u32) -> Option<libc::speed_t> {
    Some(match baud {
        50 => libc::B50,
        75 => libc::B75,
        110 => libc::B110,
        134 => libc::B134,
        150 => libc::B150,
        200 => libc::B200,
        300 => libc::B300,
        600 => libc::B600,
        1200 => libc::B1200,
        1800 => libc::B1800,
        2400 => libc::B2400,
        4800 => libc::B4800,
        9600 => libc::B9600,
        19_200 => libc::B19200,
        38_400 => libc::B38400,
        57_600 => libc::B57600,
        115_200 => libc::B115200,
        230_400 => libc::B230400,
        460_800 => libc::B460800,
        500_000 => libc::B500000,
        576_000 => libc::B576000,
        921_600 => libc::B921600,
        1_000_000 => libc::B1000000,
        1_152_000 => libc::B1152000,
        1_500_000 => libc::B1500000,
        2_000_000 => libc::B2000000,
        2_500_000 => libc::B2500000,
        3_000_000 => libc::B3000000,
        3_500_000 => libc::B3500000,
        4_000_000 => libc::B4000000,
        _ => return None,
    })
}

/// Opens and sets up the port of `cfg` with TCGETS/TCSETS, then hands the descriptor to
/// the serial crate, which takes it exclusively (TIOCEXCL and an exclusive flock) as
/// its own open does.
pub(crate) fn open(cfg: &SerialConfig) -> Result<serialport::TTYPort, tokio_serial::Error> {
    let rate = speed(cfg.baud_rate).ok_or_else(|| {
        tokio_serial::Error::new(
            ErrorKind::InvalidInput,
            format!(
                "baud rate {} needs termios2 (TCSETS2), which this kernel or emulator lacks; \
                 it can set the standard rates only (9600, 19200, 38400, 57600, 115200, ...)",
                cfg.baud_rate
            ),
        )
    })?;
    let file = open_nonblocking(&cfg.path)?;
    let fd = file.as_raw_fd();
    let mut t = get(fd)?;
    configure(&mut t, cfg, rate);
    set(fd, &t)?;
    // SAFETY: the descriptor is open and given up by `file`, so the port is its one owner.
    #[allow(unsafe_code)]
    Ok(unsafe { serialport::TTYPort::from_raw_fd(file.into_raw_fd()) })
}

/// What the serial crate sets on a port, in classic termios: raw mode, the receiver on,
/// modem lines ignored for opening, then the line settings and the speed.
fn configure(t: &mut libc::termios, cfg: &SerialConfig, rate: libc::speed_t) {
    // SAFETY: cfmakeraw and cfset*speed only change fields of the `termios` they are given.
    #[allow(unsafe_code)]
    unsafe {
        libc::cfmakeraw(t);
        libc::cfsetispeed(t, rate);
        libc::cfsetospeed(t, rate);
    }
    t.c_cflag |= libc::CREAD | libc::CLOCAL;
    t.c_cflag &= !libc::CSIZE;
    t.c_cflag |= if cfg.data_bits == 7 {
        libc::CS7
    } else {
        libc::CS8
    };
    match cfg.parity {
        Parity::None => {
            t.c_cflag &= !(libc::PARENB | libc::PARODD);
            t.c_iflag &= !libc::INPCK;
            t.c_iflag |= libc::IGNPAR;
        }
        Parity::Odd => {
            t.c_cflag |= libc::PARENB | libc::PARODD;
            t.c_iflag |= libc::INPCK;
            t.c_iflag &= !libc::IGNPAR;
        }
        Parity::Even => {
            t.c_cflag &= !libc::PARODD;
            t.c_cflag |= libc::PARENB;
            t.c_iflag |= libc::INPCK;
            t.c_iflag &= !libc::IGNPAR;
        }
    }
    if cfg.stop_bits == 2 {
        t.c_cflag |= libc::CSTOPB;
    } else {
        t.c_cflag &= !libc::CSTOPB;
    }
    match cfg.flow_control {
        FlowControl::None => {
            t.c_iflag &= !(libc::IXON | libc::IXOFF);
            t.c_cflag &= !libc::CRTSCTS;
        }
        FlowControl::Software => {
            t.c_iflag |= libc::IXON | libc::IXOFF;
            t.c_cflag &= !libc::CRTSCTS;
        }
        FlowControl::Hardware => {
            t.c_iflag &= !(libc::IXON | libc::IXOFF);
            t.c_cflag |= libc::CRTSCTS;
        }
    }
}

/// Opened as the serial crate opens a port: read and write, not as the controlling
/// terminal, without waiting for the carrier.
fn open_nonblocking(path: &str) -> io::Result<File> {
    OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags(libc::O_NOCTTY | libc::O_NONBLOCK)
        .open(path)
}

/// TCSETS at once, through the C library's tcsetattr.
pub(crate) fn set(fd: RawFd, t: &libc::termios) -> io::Result<()> {
    // SAFETY: `t` is a whole `struct termios`, read for the call; `fd` is open.
    #[allow(unsafe_code)]
    let r = unsafe { libc::tcsetattr(fd, libc::TCSANOW, t) };
    if r == 0 {
        Ok(())
    } else {
        Err(io::Error::last_os_error())
    }
}

/// TCGETS2: the terminal's settings as termios2 has them (speeds as numbers); on a
/// pty's master, its device end's. The one reader of termios2 (the RS-485 switch and
/// the virtual wire's ptys call it too); an error where the kernel has none.
pub(crate) fn get2(fd: RawFd) -> io::Result<libc::termios2> {
    let mut t = std::mem::MaybeUninit::<libc::termios2>::zeroed();
    // SAFETY: TCGETS2 writes at most one `struct termios2` into `t`, which is that size
    // and lives for the call.
    #[allow(unsafe_code)]
    let r = unsafe { libc::ioctl(fd, libc::TCGETS2 as _, t.as_mut_ptr()) };
    if r != 0 {
        return Err(io::Error::last_os_error());
    }
    // SAFETY: zeroed, then filled by a TCGETS2 that succeeded (and a zeroed termios2,
    // integers only, is a valid one anyway).
    #[allow(unsafe_code)]
    Ok(unsafe { t.assume_init() })
}

/// TCGETS, through the C library's tcgetattr.
pub(crate) fn get(fd: RawFd) -> io::Result<libc::termios> {
    let mut t = std::mem::MaybeUninit::<libc::termios>::zeroed();
    // SAFETY: tcgetattr fills the `struct termios` it is given; `fd` is open.
    #[allow(unsafe_code)]
    let r = unsafe { libc::tcgetattr(fd, t.as_mut_ptr()) };
    if r != 0 {
        return Err(io::Error::last_os_error());
    }
    // SAFETY: zeroed, then filled by a successful tcgetattr.
    #[allow(unsafe_code)]
    Ok(unsafe { t.assume_init() })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use std::io::{Read, Write};
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    /// A pty pair: the master as a file, the slave's path.
    pub(crate) fn pty() -> (File, String) {
        // SAFETY: posix_openpt returns a new descriptor or -1; on success it is owned by
        // the File below, and ptsname's string is copied before anything else runs.
        #[allow(unsafe_code)]
        unsafe {
            let master = libc::posix_openpt(libc::O_RDWR | libc::O_NOCTTY);
            assert!(master >= 0);
            assert_eq!(libc::grantpt(master), 0);
            assert_eq!(libc::unlockpt(master), 0);
            let name = std::ffi::CStr::from_ptr(libc::ptsname(master))
                .to_string_lossy()
                .into_owned();
            (File::from_raw_fd(master), name)
        }
    }

    fn cfg(path: &str, baud: u32) -> SerialConfig {
        SerialConfig {
            path: path.to_owned(),
            baud_rate: baud,
            data_bits: 7,
            parity: Parity::Even,
            stop_bits: 2,
            flow_control: FlowControl::None,
            ..SerialConfig::default()
        }
    }

    #[test]
    fn the_standard_rates_have_their_constants_and_others_none() {
        assert_eq!(speed(19_200), Some(libc::B19200));
        assert_eq!(speed(115_200), Some(libc::B115200));
        assert_eq!(speed(4_000_000), Some(libc::B4000000));
        assert_eq!(speed(19_000), None);
        assert_eq!(speed(250_000), None);
    }

    /// This kernel has termios2: the probe must not send a pty here, nor a file that is
    /// no terminal at all.
    #[test]
    fn the_probe_finds_termios2_on_this_kernel_and_no_terminal_in_a_file() {
        let (_master, slave) = pty();
        assert!(!termios2_missing(&slave));
        let file = tempfile::NamedTempFile::new().unwrap();
        assert!(!termios2_missing(file.path().to_str().unwrap()));
        assert!(!termios2_missing("/nonexistent/mbgate-port"));
    }

    /// The line settings as set on a UART: 7E2 without flow control, 8O1 with RTS/CTS,
    /// 8N1 with XON/XOFF (a pty keeps none of them: the kernel holds it at CS8, no
    /// parity, whatever is set).
    #[test]
    fn the_line_settings_are_those_of_the_configuration() {
        let (_master, slave) = pty();
        let file = open_nonblocking(&slave).unwrap();
        let mut t = get(file.as_raw_fd()).unwrap();
        configure(&mut t, &cfg(&slave, 19_200), libc::B19200);
        assert_eq!(t.c_cflag & libc::CSIZE, libc::CS7);
        assert_eq!(t.c_cflag & (libc::PARENB | libc::PARODD), libc::PARENB);
        assert_eq!(t.c_iflag & (libc::INPCK | libc::IGNPAR), libc::INPCK);
        assert_ne!(t.c_cflag & libc::CSTOPB, 0);
        assert_eq!(t.c_cflag & libc::CRTSCTS, 0);
        assert_eq!(t.c_iflag & (libc::IXON | libc::IXOFF), 0);
        assert_eq!(
            t.c_cflag & (libc::CREAD | libc::CLOCAL),
            libc::CREAD | libc::CLOCAL
        );
        // SAFETY: cfget*speed read the `termios` they are given.
        #[allow(unsafe_code)]
        let ospeed = unsafe { libc::cfgetospeed(&t) };
        assert_eq!(ospeed, libc::B19200);

        let odd = SerialConfig {
            data_bits: 8,
            parity: Parity::Odd,
            stop_bits: 1,
            flow_control: FlowControl::Hardware,
            ..cfg(&slave, 9600)
        };
        configure(&mut t, &odd, libc::B9600);
        assert_eq!(t.c_cflag & libc::CSIZE, libc::CS8);
        assert_eq!(
            t.c_cflag & (libc::PARENB | libc::PARODD),
            libc::PARENB | libc::PARODD
        );
        assert_eq!(t.c_cflag & libc::CSTOPB, 0);
        assert_ne!(t.c_cflag & libc::CRTSCTS, 0);

        let soft = SerialConfig {
            data_bits: 8,
            parity: Parity::None,
            stop_bits: 1,
            flow_control: FlowControl::Software,
            ..cfg(&slave, 9600)
        };
        configure(&mut t, &soft, libc::B9600);
        assert_eq!(t.c_cflag & (libc::PARENB | libc::PARODD), 0);
        assert_eq!(t.c_iflag & (libc::INPCK | libc::IGNPAR), libc::IGNPAR);
        assert_eq!(t.c_cflag & libc::CRTSCTS, 0);
        assert_eq!(
            t.c_iflag & (libc::IXON | libc::IXOFF),
            libc::IXON | libc::IXOFF
        );
    }

    /// The classic open on a pty: the speed read back with tcgetattr is the configured
    /// one, the port is raw and exclusive (TIOCEXCL, read back with TIOCGEXCL: root,
    /// which runs these tests in CI, would open it all the same), and bytes pass both
    /// ways.
    #[tokio::test]
    async fn a_port_opened_the_classic_way_has_its_settings_and_carries_bytes() {
        let (mut master, slave) = pty();
        let mut port =
            tokio_serial::SerialStream::try_from(open(&cfg(&slave, 38_400)).unwrap()).unwrap();
        let t = get(port.as_raw_fd()).unwrap();
        // SAFETY: cfget*speed read the `termios` they are given.
        #[allow(unsafe_code)]
        let (ispeed, ospeed) = unsafe { (libc::cfgetispeed(&t), libc::cfgetospeed(&t)) };
        assert_eq!((ispeed, ospeed), (libc::B38400, libc::B38400));
        assert_eq!(t.c_lflag & (libc::ICANON | libc::ECHO), 0, "raw");
        assert_ne!(t.c_cflag & libc::CREAD, 0);
        let mut excl: libc::c_int = 0;
        // SAFETY: TIOCGEXCL writes one int into `excl`; the port's descriptor is open.
        #[allow(unsafe_code)]
        let r = unsafe { libc::ioctl(port.as_raw_fd(), libc::TIOCGEXCL as _, &mut excl) };
        assert_eq!((r, excl), (0, 1), "TIOCEXCL set");

        AsyncWriteExt::write_all(&mut port, &[0x01, 0x03, 0x00, 0x00])
            .await
            .unwrap();
        let mut got = [0u8; 4];
        master.read_exact(&mut got).unwrap();
        assert_eq!(got, [0x01, 0x03, 0x00, 0x00]);
        master.write_all(&[0x2A, 0x55]).unwrap();
        let mut back = [0u8; 2];
        let read = AsyncReadExt::read_exact(&mut port, &mut back);
        tokio::time::timeout(std::time::Duration::from_secs(5), read)
            .await
            .expect("the bytes from the other end arrive")
            .unwrap();
        assert_eq!(back, [0x2A, 0x55]);
    }

    #[test]
    fn a_rate_without_a_constant_is_refused_by_name() {
        let (_master, slave) = pty();
        let e = open(&cfg(&slave, 250_000)).unwrap_err();
        assert_eq!(e.kind, ErrorKind::InvalidInput);
        assert!(
            e.description.contains("baud rate 250000 needs termios2"),
            "{e}"
        );
    }

    /// TCGETS2 reads a terminal's speed as a number, the same through the pty's master
    /// as through its device (a new pty's 38400 baud, the kernel's `tty_std_termios`);
    /// a pipe is no terminal.
    #[test]
    fn termios2_is_read_from_either_end_and_refused_off_a_tty() {
        let (master, path) = pty();
        let device = OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags(libc::O_NOCTTY)
            .open(&path)
            .unwrap();
        assert_eq!(get2(device.as_raw_fd()).unwrap().c_ospeed, 38400);
        assert_eq!(get2(master.as_raw_fd()).unwrap().c_ospeed, 38400);
        let (r, _w) = std::io::pipe().unwrap();
        let e = get2(r.as_raw_fd()).unwrap_err();
        assert_eq!(e.raw_os_error(), Some(libc::ENOTTY), "{e}");
    }
}
