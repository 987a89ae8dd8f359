//! What a serial port is, found at each open (docs/reliability.md "Knowing the
//! wire"; the kinds themselves are `port/kind.rs`): a pseudo-terminal, a native UART
//! (its driver, its receive FIFO's trigger level), a USB adapter (its driver, its
//! latency timer) or a tty of no known kind; and the driver's low latency turned on.
//!
//! Read from the open descriptor (its device number; TIOCGSERIAL and TIOCSSERIAL) and
//! from sysfs, only ever read: it works where /sys is read-only (the hardened systemd
//! units), and where /sys cannot be read at all it falls back on the device number.

use crate::line::port::kind::{LowLatency, Medium, PortInfo};
use std::os::fd::RawFd;
use std::path::{Path, PathBuf};

/// What sysfs tells about a tty (`/sys/dev/char/MAJOR:MINOR`).
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub(crate) struct SysFacts {
    /// The device hangs off a USB bus.
    pub(crate) usb: bool,
    /// The driver that owns it (the first up its device path that is not the serial
    /// core's own `port` or `ctrl`).
    pub(crate) driver: Option<String>,
    /// It is a port of the serial core (it has `uartclk`): a native UART.
    pub(crate) serial_core: bool,
    /// `rx_trig_bytes` (8250 family).
    pub(crate) trigger: Option<u32>,
    /// `latency_timer` (FTDI).
    pub(crate) latency_ms: Option<u32>,
}

/// The kind of the tty with this device number, given what sysfs said (`None`: it
/// could not be read) and whether low latency is on.
pub(crate) fn classify(
    major: u32,
    minor: u32,
    sys: Option<&SysFacts>,
    low_latency: bool,
) -> Medium {
    // Unix 98 pty slaves (/dev/pts/N), and the legacy BSD ones.
    if (136..=143).contains(&major) || major == 3 {
        return Medium::Pty;
    }
    let Some(sys) = sys else {
        // No sysfs: the well-known device numbers (Documentation/admin-guide/devices.txt).
        return match (major, minor) {
            (4, 64..) | (204, _) => Medium::Uart {
                driver: None,
                trigger: None,
            },
            (188, _) | (166, _) => Medium::Usb {
                driver: None,
                latency_ms: None,
            },
            _ => Medium::Other { driver: None },
        };
    };
    if sys.usb {
        // An FTDI adapter with low latency on hands bytes over every 1 ms, whatever
        // its latency_timer was set to.
        let ftdi = sys.driver.as_deref() == Some("ftdi_sio");
        let latency_ms = if ftdi && low_latency {
            Some(1)
        } else {
            sys.latency_ms
        };
        return Medium::Usb {
            driver: sys.driver.clone(),
            latency_ms,
        };
    }
    if sys.serial_core {
        return Medium::Uart {
            driver: sys.driver.clone(),
            trigger: sys.trigger,
        };
    }
    Medium::Other {
        driver: sys.driver.clone(),
    }
}

/// Reads what sysfs (at `root`, `/sys` but in tests) says about the tty `major:minor`;
/// `None` when it cannot be read.
pub(crate) fn sys_facts(root: &Path, major: u32, minor: u32) -> Option<SysFacts> {
    let tty = std::fs::canonicalize(root.join(format!("dev/char/{major}:{minor}"))).ok()?;
    let device = std::fs::canonicalize(tty.join("device")).ok();
    let read_u32 =
        |p: PathBuf| -> Option<u32> { std::fs::read_to_string(p).ok()?.trim().parse().ok() };
    let usb = device.as_ref().is_some_and(|d| {
        d.components()
            .any(|c| c.as_os_str().to_string_lossy().starts_with("usb"))
    });
    Some(SysFacts {
        usb,
        driver: device.as_deref().and_then(|d| driver_of(root, d)),
        serial_core: tty.join("uartclk").exists(),
        trigger: read_u32(tty.join("rx_trig_bytes")),
        latency_ms: device.and_then(|d| read_u32(d.join("latency_timer"))),
    })
}

/// The driver of `device` or of the first device above it that has one, past the
/// serial core's own (`port`, `ctrl`: since Linux 6.5 a native UART's tty hangs off
/// them), up to `root`.
fn driver_of(root: &Path, device: &Path) -> Option<String> {
    let mut at = Some(device);
    while let Some(dir) = at.filter(|d| d.starts_with(root) && *d != root) {
        if let Ok(link) = std::fs::read_link(dir.join("driver")) {
            let name = link.file_name()?.to_string_lossy().into_owned();
            if name != "port" && name != "ctrl" {
                return Some(name);
            }
        }
        at = dir.parent();
    }
    None
}

/// The device number of the open file `fd`, as (major, minor); `None` if not a
/// character device.
fn device_number(fd: RawFd) -> Option<(u32, u32)> {
    // SAFETY: fstat writes one `struct stat`, which `st` is, for the duration of the
    // call; `fd` is open.
    #[allow(unsafe_code)]
    let st = unsafe {
        let mut st = std::mem::MaybeUninit::<libc::stat>::zeroed();
        if libc::fstat(fd, st.as_mut_ptr()) != 0 {
            return None;
        }
        st.assume_init()
    };
    if st.st_mode & libc::S_IFMT != libc::S_IFCHR {
        return None;
    }
    let dev = st.st_rdev;
    let major = ((dev >> 8) & 0xfff) | ((dev >> 32) & !0xfff);
    let minor = (dev & 0xff) | ((dev >> 12) & !0xff);
    Some((major as u32, minor as u32))
}

/// What the open tty `fd` is. With `low_latency`, first turns the driver's low latency
/// on (the FTDI driver then uses a 1 ms latency timer).
pub(crate) fn detect(fd: RawFd, low_latency: bool) -> PortInfo {
    let ll = if low_latency {
        match set_low_latency(fd) {
            Ok(true) => LowLatency::On,
            Ok(false) => LowLatency::Unsupported,
            Err(e) if matches!(e.raw_os_error(), Some(libc::ENOTTY) | Some(libc::EINVAL)) => {
                LowLatency::Unsupported
            }
            Err(e) => LowLatency::Refused(e.to_string()),
        }
    } else {
        LowLatency::NotAsked
    };
    let medium = match device_number(fd) {
        Some((major, minor)) => {
            let sys = sys_facts(Path::new("/sys"), major, minor);
            classify(major, minor, sys.as_ref(), ll == LowLatency::On)
        }
        None => Medium::Other { driver: None },
    };
    PortInfo {
        medium,
        low_latency: ll,
    }
}

/// What the path names, without opening it (the master line and the client, which
/// take their timing before the port opens): the device number from `stat`.
pub(crate) fn of_path(path: &str) -> Medium {
    use std::os::unix::fs::{FileTypeExt, MetadataExt};
    let Ok(meta) = std::fs::metadata(path) else {
        return Medium::Other { driver: None };
    };
    if !meta.file_type().is_char_device() {
        return Medium::Other { driver: None };
    }
    let dev = meta.rdev();
    let major = (((dev >> 8) & 0xfff) | ((dev >> 32) & !0xfff)) as u32;
    let minor = ((dev & 0xff) | ((dev >> 12) & !0xff)) as u32;
    let sys = sys_facts(Path::new("/sys"), major, minor);
    classify(major, minor, sys.as_ref(), false)
}

/// The kernel's `struct serial_struct` (linux/serial.h); libc does not define it.
#[repr(C)]
#[derive(Debug, Default)]
struct SerialStruct {
    kind: libc::c_int,
    line: libc::c_int,
    port: libc::c_uint,
    irq: libc::c_int,
    flags: libc::c_int,
    xmit_fifo_size: libc::c_int,
    custom_divisor: libc::c_int,
    baud_base: libc::c_int,
    close_delay: libc::c_ushort,
    io_type: libc::c_char,
    reserved_char: libc::c_char,
    hub6: libc::c_int,
    closing_wait: libc::c_ushort,
    closing_wait2: libc::c_ushort,
    iomem_base: usize,
    iomem_reg_shift: libc::c_ushort,
    port_high: libc::c_uint,
    iomap_base: libc::c_ulong,
}

/// ASYNCB_LOW_LATENCY (linux/tty_flags.h): one of the flags a user may change without
/// privilege (ASYNC_USR_MASK).
const ASYNC_LOW_LATENCY: libc::c_int = 1 << 13;

fn get_serial(fd: RawFd) -> std::io::Result<SerialStruct> {
    let mut ss = SerialStruct::default();
    // SAFETY: TIOCGSERIAL writes one `struct serial_struct`, which `ss` is, for the
    // duration of the call.
    #[allow(unsafe_code)]
    let r = unsafe { libc::ioctl(fd, libc::TIOCGSERIAL as _, &mut ss as *mut SerialStruct) };
    if r == 0 {
        Ok(ss)
    } else {
        Err(std::io::Error::last_os_error())
    }
}

/// Turns the driver's low latency on (`setserial low_latency`): the settings as the
/// driver gives them, with that one flag added, which needs no privilege (only the
/// flags of ASYNC_USR_MASK change). True if the driver kept it (read back); an error
/// if it has no such setting (ENOTTY: a pty) or refused.
pub(crate) fn set_low_latency(fd: RawFd) -> std::io::Result<bool> {
    let mut ss = get_serial(fd)?;
    if ss.flags & ASYNC_LOW_LATENCY != 0 {
        return Ok(true);
    }
    ss.flags |= ASYNC_LOW_LATENCY;
    // SAFETY: TIOCSSERIAL reads one `struct serial_struct`, which `ss` is, for the
    // duration of the call.
    #[allow(unsafe_code)]
    let r = unsafe { libc::ioctl(fd, libc::TIOCSSERIAL as _, &ss as *const SerialStruct) };
    if r != 0 {
        return Err(std::io::Error::last_os_error());
    }
    Ok(get_serial(fd)?.flags & ASYNC_LOW_LATENCY != 0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn serial_struct_has_the_kernels_layout() {
        // x86_64 and aarch64 (LP64): 72 bytes, the pointer at 48.
        if std::mem::size_of::<usize>() == 8 {
            assert_eq!(std::mem::size_of::<SerialStruct>(), 72);
            assert_eq!(std::mem::offset_of!(SerialStruct, hub6), 36);
            assert_eq!(std::mem::offset_of!(SerialStruct, iomem_base), 48);
            assert_eq!(std::mem::offset_of!(SerialStruct, iomap_base), 64);
        }
    }

    #[test]
    fn device_numbers_without_sysfs() {
        assert_eq!(classify(136, 3, None, false), Medium::Pty);
        assert_eq!(classify(143, 9, None, true), Medium::Pty);
        let uart = Medium::Uart {
            driver: None,
            trigger: None,
        };
        assert_eq!(classify(4, 64, None, false), uart, "ttyS0");
        assert_eq!(classify(204, 64, None, false), uart, "ttyAMA0");
        assert_eq!(
            classify(4, 1, None, false),
            Medium::Other { driver: None },
            "tty1, a console"
        );
        let usb = Medium::Usb {
            driver: None,
            latency_ms: None,
        };
        assert_eq!(classify(188, 0, None, true), usb, "ttyUSB0: which driver?");
        assert_eq!(classify(166, 0, None, false), usb, "ttyACM0");
    }

    #[test]
    fn sysfs_facts_decide_and_low_latency_sets_an_ftdis_timer() {
        let ftdi = SysFacts {
            usb: true,
            driver: Some("ftdi_sio".into()),
            latency_ms: Some(16),
            ..SysFacts::default()
        };
        let usb = |ms| Medium::Usb {
            driver: Some("ftdi_sio".into()),
            latency_ms: ms,
        };
        assert_eq!(classify(188, 0, Some(&ftdi), false), usb(Some(16)));
        assert_eq!(classify(188, 0, Some(&ftdi), true), usb(Some(1)));
        let cp210x = SysFacts {
            usb: true,
            driver: Some("cp210x".into()),
            ..SysFacts::default()
        };
        assert_eq!(
            classify(188, 1, Some(&cp210x), true),
            Medium::Usb {
                driver: Some("cp210x".into()),
                latency_ms: None
            },
            "only the FTDI driver is known to map low latency to its timer"
        );
        let pl011 = SysFacts {
            driver: Some("uart-pl011".into()),
            serial_core: true,
            ..SysFacts::default()
        };
        assert_eq!(
            classify(204, 64, Some(&pl011), true),
            Medium::Uart {
                driver: Some("uart-pl011".into()),
                trigger: None
            }
        );
        assert_eq!(
            classify(216, 0, Some(&SysFacts::default()), false),
            Medium::Other { driver: None },
            "rfcomm"
        );
    }

    /// An FTDI adapter as sysfs shows it, built in a temporary tree.
    #[test]
    fn sysfs_tree_of_an_ftdi_adapter_and_of_a_uart() {
        use std::os::unix::fs::symlink;
        let root = tempfile::tempdir().unwrap();
        let r = root.path();
        let port = r.join("devices/pci0000:00/usb1/1-1/1-1:1.0/ttyUSB0");
        let tty = port.join("tty/ttyUSB0");
        std::fs::create_dir_all(&tty).unwrap();
        std::fs::create_dir_all(r.join("bus/usb-serial/drivers/ftdi_sio")).unwrap();
        std::fs::create_dir_all(r.join("dev/char")).unwrap();
        symlink(&tty, r.join("dev/char/188:0")).unwrap();
        symlink(&port, tty.join("device")).unwrap();
        symlink(
            r.join("bus/usb-serial/drivers/ftdi_sio"),
            port.join("driver"),
        )
        .unwrap();
        std::fs::write(port.join("latency_timer"), "16\n").unwrap();
        let facts = sys_facts(r, 188, 0).unwrap();
        assert_eq!(
            facts,
            SysFacts {
                usb: true,
                driver: Some("ftdi_sio".into()),
                serial_core: false,
                trigger: None,
                latency_ms: Some(16),
            }
        );
        // A native UART of Linux 6.5 and later: the tty hangs off the serial core's
        // `port`, whose parent the real driver owns.
        let dev = r.join("devices/pnp0/00:00");
        let base = dev.join("00:00:0/00:00:0.0");
        let tty = base.join("tty/ttyS0");
        std::fs::create_dir_all(&tty).unwrap();
        for d in [
            "serial-base/drivers/port",
            "serial-base/drivers/ctrl",
            "pnp/drivers/serial",
        ] {
            std::fs::create_dir_all(r.join("bus").join(d)).unwrap();
        }
        symlink(&tty, r.join("dev/char/4:64")).unwrap();
        symlink(&base, tty.join("device")).unwrap();
        symlink(r.join("bus/serial-base/drivers/port"), base.join("driver")).unwrap();
        symlink(
            r.join("bus/serial-base/drivers/ctrl"),
            dev.join("00:00:0/driver"),
        )
        .unwrap();
        symlink(r.join("bus/pnp/drivers/serial"), dev.join("driver")).unwrap();
        std::fs::write(tty.join("uartclk"), "1843200\n").unwrap();
        std::fs::write(tty.join("rx_trig_bytes"), "8\n").unwrap();
        let facts = sys_facts(r, 4, 64).unwrap();
        assert_eq!(
            classify(4, 64, Some(&facts), true),
            Medium::Uart {
                driver: Some("serial".into()),
                trigger: Some(8)
            }
        );
        assert!(sys_facts(r, 4, 65).is_none(), "no such device");
    }

    /// A pty, opened: found by its device number; it has no low latency to set.
    #[test]
    fn a_pty_is_found_and_has_no_low_latency() {
        let (_master, name) = crate::line::port::serial::classic::tests::pty();
        let slave = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .open(&name)
            .unwrap();
        use std::os::fd::AsRawFd;
        let info = detect(slave.as_raw_fd(), true);
        assert_eq!(info.medium, Medium::Pty);
        assert_eq!(info.low_latency, LowLatency::Unsupported);
        assert_eq!(of_path(&name), Medium::Pty);
        assert_eq!(info.to_string(), "a pseudo-terminal (no wire)");
    }

    /// On a machine with a real UART to spare: `MBGATE_TEST_UART=/dev/ttyS1 cargo test
    /// --lib detect::tests::a_real_uart` finds it and turns its low latency on (the
    /// driver's flag, no privilege needed). Not run otherwise.
    #[test]
    fn a_real_uart_when_one_is_named() {
        let Some(path) = std::env::var_os("MBGATE_TEST_UART") else {
            return;
        };
        use std::os::fd::AsRawFd;
        use std::os::unix::fs::OpenOptionsExt;
        let f = std::fs::OpenOptions::new()
            .read(true)
            .custom_flags(libc::O_NONBLOCK | libc::O_NOCTTY)
            .open(&path)
            .unwrap();
        let before = get_serial(f.as_raw_fd()).unwrap().flags;
        let info = detect(f.as_raw_fd(), true);
        eprintln!("{}: {info}", path.to_string_lossy());
        assert!(matches!(info.medium, Medium::Uart { .. }), "{info:?}");
        assert_eq!(info.low_latency, LowLatency::On);
        // Put back as found.
        let mut ss = get_serial(f.as_raw_fd()).unwrap();
        ss.flags = before;
        #[allow(unsafe_code)]
        unsafe {
            libc::ioctl(
                f.as_raw_fd(),
                libc::TIOCSSERIAL as _,
                &ss as *const SerialStruct,
            );
        }
    }
}
