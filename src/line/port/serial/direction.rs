//! The switch of an RS-485 transmitter that the gateway drives itself
//! (`serial.direction`, docs/rs485.md): RTS on the port (TIOCMBIS, TIOCMBIC) or a GPIO
//! line through the GPIO character device, either polarity; taken at each open with
//! an error that names the setting, and left off when dropped. And whether the UART's
//! transmitter is empty, its last stop bit gone (TIOCSERGETLSR).

use crate::config::{Direction, GpioLine, SerialConfig};
use std::io;
use std::os::fd::RawFd;
use std::path::{Path, PathBuf};

/// What switches a transmitter on (to send) and off (to receive).
pub trait Switch: Send {
    /// On to send, off to receive.
    fn set(&mut self, transmit: bool) -> io::Result<()>;
}

/// RTS of a port: asserted (TIOCMBIS) or released (TIOCMBIC).
pub(crate) trait ModemLines: Send {
    /// Asserts RTS, or releases it.
    fn rts(&mut self, asserted: bool) -> io::Result<()>;
}

/// A GPIO line requested as an output: driven high or low.
pub(crate) trait OutputLine: Send {
    /// Drives the line high, or low.
    fn drive(&mut self, high: bool) -> io::Result<()>;
}

/// The transmitter switched by RTS: asserted while sending, or with `invert` released
/// while sending (mbusd's `-t` and `-r`).
pub(crate) struct Rts<M> {
    pub(crate) lines: M,
    pub(crate) invert: bool,
}

impl<M: ModemLines> Switch for Rts<M> {
    fn set(&mut self, transmit: bool) -> io::Result<()> {
        self.lines.rts(transmit != self.invert)
    }
}

/// The transmitter switched by a GPIO line: high while sending, or with `invert` low.
pub(crate) struct Gpio<L> {
    pub(crate) line: L,
    pub(crate) invert: bool,
}

impl<L: OutputLine> Switch for Gpio<L> {
    fn set(&mut self, transmit: bool) -> io::Result<()> {
        self.line.drive(transmit != self.invert)
    }
}

/// The switch as an open port holds it: switched off when dropped, at shutdown or
/// when the port is lost, before the line (a GPIO request) is released, so the
/// transmitter is left off and the bus free.
pub(crate) struct Transmitter {
    switch: Box<dyn Switch>,
}

impl Transmitter {
    /// Holds `switch`, switching it off first: a transmitter left on by a process
    /// before would hold the bus.
    pub(crate) fn new(mut switch: Box<dyn Switch>) -> io::Result<Transmitter> {
        switch.set(false)?;
        Ok(Transmitter { switch })
    }

    /// On to send, off to receive.
    pub(crate) fn set(&mut self, transmit: bool) -> io::Result<()> {
        self.switch.set(transmit)
    }
}

impl Drop for Transmitter {
    fn drop(&mut self) {
        if let Err(e) = self.switch.set(false) {
            tracing::warn!("could not switch the RS-485 transmitter off: {e}");
        }
    }
}

/// Why the transmitter's switch could not be taken at an open: each names its setting.
#[derive(Debug, thiserror::Error)]
pub(crate) enum DirectionError {
    /// RTS cannot be switched: a pseudo-terminal, or a driver without modem lines.
    #[error(
        "serial.direction = \"rts\": {path} has no RTS to switch (a pseudo-terminal, or a \
         driver without modem lines): {source}"
    )]
    NoModemLines {
        /// The port.
        path: String,
        /// What TIOCMBIC answered.
        source: io::Error,
    },
    /// No GPIO chip by that path, name or label.
    #[error(
        "serial.direction_gpio_chip = {chip:?}: no GPIO chip by that path, name or label \
         (chips here: {found})"
    )]
    NoChip {
        /// As configured.
        chip: String,
        /// The chips there are, with their labels.
        found: String,
    },
    /// The chip is there but cannot be opened.
    #[error(
        "serial.direction_gpio_chip: {path}: {source} (the gateway needs the gpio group, or \
         DeviceAllow=/dev/gpiochip* in its unit: docs/raspberry-pi.md)"
    )]
    ChipAccess {
        /// The chip's device.
        path: String,
        /// Why it could not be opened.
        source: io::Error,
    },
    /// No line at that offset.
    #[error("serial.direction_gpio_line = {offset}: {chip} has lines 0 to {last} only")]
    NoLine {
        /// As configured.
        offset: u32,
        /// The chip's device.
        chip: String,
        /// Its last offset.
        last: i64,
    },
    /// No line of that name.
    #[error("serial.direction_gpio_line = {name:?}: no line of that name on {chip} (gpioinfo lists the names)")]
    NoNamedLine {
        /// As configured.
        name: String,
        /// Where it was looked for.
        chip: String,
    },
    /// Another process (or a driver) holds the line.
    #[error(
        "serial.direction_gpio_line: line {offset} of {chip} is held by another process or \
         driver ({consumer:?}); the gateway needs it alone"
    )]
    LineBusy {
        /// The line.
        offset: u32,
        /// The chip's device.
        chip: String,
        /// Who holds it, as the kernel says.
        consumer: String,
    },
    /// Anything else the GPIO character device refused.
    #[error("serial.direction_gpio_line: line {offset} of {chip}: {source}")]
    Gpio {
        /// The line.
        offset: u32,
        /// The chip's device.
        chip: String,
        /// What the GPIO character device answered.
        source: gpiocdev::Error,
    },
}

/// Does the gateway switch the RS-485 transmitter of a serial port `cfg` describes:
/// the one place this is decided, for the port that takes the switch at each open
/// (`take`) and the relay that times its delays (docs/rs485.md). `None`: the
/// transceiver switches itself, or the kernel does (RS-485 mode).
pub(crate) fn gateway_switches(cfg: &SerialConfig) -> bool {
    cfg.direction != Direction::None
}

/// The transmitter's switch `cfg` asks for on the open port `fd`, switched off; none
/// where the gateway switches nothing.
pub(crate) fn take(cfg: &SerialConfig, fd: RawFd) -> Result<Option<Transmitter>, DirectionError> {
    if !gateway_switches(cfg) {
        return Ok(None);
    }
    match cfg.direction {
        // Decided above.
        Direction::None => Ok(None),
        Direction::Rts => {
            let rts = Rts {
                lines: RtsLine(fd),
                invert: cfg.direction_invert,
            };
            let no_lines = |source| DirectionError::NoModemLines {
                path: cfg.path.clone(),
                source,
            };
            let transmitter = Transmitter::new(Box::new(rts)).map_err(no_lines)?;
            if cfg.direction_invert {
                // Released RTS is "send" to an inverted transmitter: the kernel must
                // not release it when the port closes (at a stop, a lost port, a
                // restart), where the gateway left it asserted, off.
                keep_modem_lines_on_close(fd).map_err(no_lines)?;
            }
            Ok(Some(transmitter))
        }
        Direction::Gpio => {
            let line = request_line(cfg)?;
            let (offset, chip) = (line.offset, line.request.chip_path());
            let gpio = Gpio {
                line,
                invert: cfg.direction_invert,
            };
            Transmitter::new(Box::new(gpio))
                .map(Some)
                .map_err(|source| DirectionError::Gpio {
                    offset,
                    chip: chip.display().to_string(),
                    source: gpiocdev::Error::from(source),
                })
        }
    }
}

/// RTS of the open port.
struct RtsLine(RawFd);

impl ModemLines for RtsLine {
    fn rts(&mut self, asserted: bool) -> io::Result<()> {
        let bits: libc::c_int = libc::TIOCM_RTS;
        let op = if asserted {
            libc::TIOCMBIS
        } else {
            libc::TIOCMBIC
        };
        // SAFETY: TIOCMBIS and TIOCMBIC read one int, which `bits` is, for the
        // duration of the call; `self.0` is the open port.
        #[allow(unsafe_code)]
        let r = unsafe { libc::ioctl(self.0, op as _, &bits as *const libc::c_int) };
        if r == 0 {
            Ok(())
        } else {
            Err(io::Error::last_os_error())
        }
    }
}

/// Clears HUPCL on the open port `fd`: its last close leaves the modem lines as they
/// are instead of lowering DTR and RTS (termios(3), "HUPCL"). Through termios2, as
/// the port was set; classic termios where the kernel has none
/// (`classic::termios2_missing`).
pub(crate) fn keep_modem_lines_on_close(fd: RawFd) -> io::Result<()> {
    let Ok(mut t) = super::classic::get2(fd) else {
        let mut t = super::classic::get(fd)?;
        t.c_cflag &= !libc::HUPCL;
        return super::classic::set(fd, &t);
    };
    t.c_cflag &= !libc::HUPCL;
    // SAFETY: TCSETS2 reads one `struct termios2`, which `t` is.
    #[allow(unsafe_code)]
    let r = unsafe { libc::ioctl(fd, libc::TCSETS2 as _, &t as *const libc::termios2) };
    if r == 0 {
        Ok(())
    } else {
        Err(io::Error::last_os_error())
    }
}

/// `TIOCSER_TEMT` (linux/serial.h; not in libc for every target): the transmitter
/// is empty, shift register included.
const TIOCSER_TEMT: libc::c_uint = 0x01;

/// Has the last stop bit left the UART (TIOCSERGETLSR reports TIOCSER_TEMT)? An
/// error where the driver cannot tell (a pty, most USB adapters but FTDI's).
pub(crate) fn transmitter_empty(fd: RawFd) -> io::Result<bool> {
    let mut lsr: libc::c_uint = 0;
    // SAFETY: TIOCSERGETLSR writes one unsigned int, which `lsr` is, for the duration
    // of the call.
    #[allow(unsafe_code)]
    let r = unsafe { libc::ioctl(fd, libc::TIOCSERGETLSR as _, &mut lsr as *mut libc::c_uint) };
    if r == 0 {
        Ok(lsr & TIOCSER_TEMT != 0)
    } else {
        Err(io::Error::last_os_error())
    }
}

/// A GPIO line requested as an output of ours.
struct Requested {
    request: gpiocdev::Request,
    offset: u32,
}

impl OutputLine for Requested {
    fn drive(&mut self, high: bool) -> io::Result<()> {
        use gpiocdev::line::Value;
        let value = if high { Value::Active } else { Value::Inactive };
        self.request
            .set_value(self.offset, value)
            .map_err(io::Error::other)
    }
}

/// The chips there are, `gpiochip0 [pinctrl-bcm2711]`, for an error.
fn chips_here() -> String {
    let chips = gpiocdev::chip::chips().unwrap_or_default();
    if chips.is_empty() {
        return "none".into();
    }
    let named: Vec<String> = chips
        .iter()
        .map(|p| {
            let label = gpiocdev::Chip::from_path(p)
                .and_then(|c| c.info())
                .map(|i| i.label)
                .unwrap_or_else(|_| "?".into());
            format!("{} [{label}]", p.display())
        })
        .collect();
    named.join(", ")
}

/// The chip `spec` names: a path, a name under /dev, or a label; "" is gpiochip0.
fn find_chip(spec: &str) -> Result<PathBuf, DirectionError> {
    let spec = spec.trim();
    let path = match spec {
        "" => PathBuf::from("/dev/gpiochip0"),
        s if s.contains('/') => PathBuf::from(s),
        s => Path::new("/dev").join(s),
    };
    let no_chip = || DirectionError::NoChip {
        chip: if spec.is_empty() {
            "gpiochip0".to_owned()
        } else {
            spec.to_owned()
        },
        found: chips_here(),
    };
    if path.exists() {
        // Open it to tell a device the gateway may not open from one that is none.
        if let Err(source) = std::fs::File::open(&path) {
            return Err(DirectionError::ChipAccess {
                path: path.display().to_string(),
                source,
            });
        }
        return gpiocdev::chip::is_chip(&path).map_err(|_| no_chip());
    }
    if spec.is_empty() || spec.contains('/') {
        return Err(no_chip());
    }
    // A label, as gpiodetect shows it.
    gpiocdev::chip::chips()
        .unwrap_or_default()
        .into_iter()
        .find(|p| {
            gpiocdev::Chip::from_path(p)
                .and_then(|c| c.info())
                .is_ok_and(|i| i.label == spec)
        })
        .ok_or_else(no_chip)
}

/// The chip and offset of the line `cfg` names: by its name on any chip, or on the
/// chip named, by name or offset (within the chip's lines).
fn find_line(cfg: &SerialConfig) -> Result<(PathBuf, u32), DirectionError> {
    let chip_spec = cfg.direction_gpio_chip.trim();
    let line = match &cfg.direction_gpio_line {
        GpioLine::Name(name) if chip_spec.is_empty() => {
            let found =
                gpiocdev::find_named_line(name).ok_or_else(|| DirectionError::NoNamedLine {
                    name: name.clone(),
                    chip: format!("any chip ({})", chips_here()),
                })?;
            return Ok((found.chip, found.info.offset));
        }
        line => line,
    };
    let chip = find_chip(chip_spec)?;
    let opened = gpiocdev::Chip::from_path(&chip).map_err(|source| DirectionError::Gpio {
        offset: 0,
        chip: chip.display().to_string(),
        source,
    })?;
    let offset = match line {
        GpioLine::Name(name) => {
            opened
                .find_line_info(name)
                .ok_or_else(|| DirectionError::NoNamedLine {
                    name: name.clone(),
                    chip: chip.display().to_string(),
                })?
                .offset
        }
        GpioLine::Offset(n) => *n,
        GpioLine::Unset => {
            // The configuration refuses direction = "gpio" without a line.
            return Err(DirectionError::NoNamedLine {
                name: String::new(),
                chip: chip.display().to_string(),
            });
        }
    };
    let lines = opened.info().map(|i| i.num_lines).unwrap_or(u32::MAX);
    if offset >= lines {
        return Err(DirectionError::NoLine {
            offset,
            chip: chip.display().to_string(),
            last: i64::from(lines) - 1,
        });
    }
    Ok((chip, offset))
}

/// The line `cfg` names, found and requested as an output at the level that keeps
/// the transmitter off.
fn request_line(cfg: &SerialConfig) -> Result<Requested, DirectionError> {
    let (chip, offset) = find_line(cfg)?;
    let chip_name = chip.display().to_string();
    if let Ok(info) = gpiocdev::Chip::from_path(&chip).and_then(|c| c.line_info(offset)) {
        if info.used {
            return Err(DirectionError::LineBusy {
                offset,
                chip: chip_name,
                consumer: info.consumer,
            });
        }
    }
    // Requested at the level that keeps the transmitter off: taking the line must not
    // put the gateway on the bus.
    let off_high = cfg.direction_invert;
    let initial = if off_high {
        gpiocdev::line::Value::Active
    } else {
        gpiocdev::line::Value::Inactive
    };
    let request = gpiocdev::Request::builder()
        .on_chip(&chip)
        .with_consumer("mbgate")
        .with_line(offset)
        .as_output(initial)
        .request()
        .map_err(|source| DirectionError::Gpio {
            offset,
            chip: chip_name,
            source,
        })?;
    Ok(Requested { request, offset })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::{Arc, Mutex};

    /// What the fakes were asked, in order.
    type Log = Arc<Mutex<Vec<&'static str>>>;

    /// RTS as TIOCMBIS and TIOCMBIC would leave it, every call logged.
    struct FakeRts(Log);
    impl ModemLines for FakeRts {
        fn rts(&mut self, asserted: bool) -> io::Result<()> {
            self.0.lock().unwrap().push(if asserted {
                "TIOCMBIS RTS"
            } else {
                "TIOCMBIC RTS"
            });
            Ok(())
        }
    }

    /// A GPIO output line, every level logged.
    struct FakeGpio(Log);
    impl OutputLine for FakeGpio {
        fn drive(&mut self, high: bool) -> io::Result<()> {
            self.0
                .lock()
                .unwrap()
                .push(if high { "high" } else { "low" });
            Ok(())
        }
    }

    /// A port without modem lines: what a pty answers.
    struct NoRts;
    impl ModemLines for NoRts {
        fn rts(&mut self, _: bool) -> io::Result<()> {
            Err(io::Error::from_raw_os_error(libc::ENOTTY))
        }
    }

    fn log() -> Log {
        Arc::new(Mutex::new(Vec::new()))
    }

    /// Both polarities of both switches: the level that sends and the one that
    /// receives; taken off, and left off when dropped while on.
    #[test]
    fn each_switch_and_polarity_sets_its_level_and_is_left_off() {
        for invert in [false, true] {
            let l = log();
            let rts = Rts {
                lines: FakeRts(l.clone()),
                invert,
            };
            let mut t = Transmitter::new(Box::new(rts)).unwrap();
            t.set(true).unwrap();
            drop(t);
            let (on, off) = if invert {
                ("TIOCMBIC RTS", "TIOCMBIS RTS")
            } else {
                ("TIOCMBIS RTS", "TIOCMBIC RTS")
            };
            assert_eq!(*l.lock().unwrap(), [off, on, off], "RTS, invert = {invert}");

            let l = log();
            let gpio = Gpio {
                line: FakeGpio(l.clone()),
                invert,
            };
            let mut t = Transmitter::new(Box::new(gpio)).unwrap();
            t.set(true).unwrap();
            t.set(false).unwrap();
            t.set(true).unwrap();
            drop(t);
            let (on, off) = if invert {
                ("low", "high")
            } else {
                ("high", "low")
            };
            assert_eq!(
                *l.lock().unwrap(),
                [off, on, off, on, off],
                "GPIO, invert = {invert}"
            );
        }
    }

    /// A port without RTS is refused when the switch is taken, not at the first request.
    #[test]
    fn a_port_without_modem_lines_is_refused_at_once() {
        let rts = Rts {
            lines: NoRts,
            invert: false,
        };
        let e = Transmitter::new(Box::new(rts)).err().expect("refused");
        assert_eq!(e.raw_os_error(), Some(libc::ENOTTY));
    }

    /// On a pty, the real thing: RTS is refused with an error naming the setting; the
    /// transmitter is said empty or the driver cannot tell, never an error taken for
    /// "still sending".
    #[test]
    fn a_pty_has_no_rts_to_switch() {
        use std::os::fd::AsRawFd;
        let (master, _) = crate::line::port::serial::classic::tests::pty();
        let fd = master.as_raw_fd();
        let cfg = SerialConfig {
            path: "/dev/ptmx".into(),
            direction: Direction::Rts,
            ..SerialConfig::default()
        };
        let e = take(&cfg, fd).err().expect("a pty has no RTS").to_string();
        assert!(
            e.starts_with("serial.direction = \"rts\": /dev/ptmx has no RTS to switch"),
            "{e}"
        );
        assert!(e.contains("Inappropriate ioctl"), "{e}");
        assert!(transmitter_empty(fd).is_err(), "a pty has no LSR");
    }

    /// A chip that is not there, by name or path, names the setting and the chips
    /// there are; a line past the chip's end, or of no such name, names its setting.
    #[test]
    fn a_missing_chip_or_line_names_its_setting() {
        let gpio = |chip: &str, line: GpioLine| SerialConfig {
            direction: Direction::Gpio,
            direction_gpio_chip: chip.into(),
            direction_gpio_line: line,
            ..SerialConfig::default()
        };
        let e = request_line(&gpio("gpiochip97", GpioLine::Offset(1)))
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.starts_with("serial.direction_gpio_chip = \"gpiochip97\": no GPIO chip"),
            "{e}"
        );
        let e = request_line(&gpio("/nonexistent/gpiochip0", GpioLine::Offset(1)))
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("no GPIO chip by that path"), "{e}");
        let e = request_line(&gpio("", GpioLine::Name("NO_SUCH_LINE_X".into())))
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.starts_with("serial.direction_gpio_line = \"NO_SUCH_LINE_X\": no line"),
            "{e}"
        );
        // The default chip, where there is none: named as gpiochip0.
        if !Path::new("/dev/gpiochip0").exists() {
            let e = request_line(&gpio("", GpioLine::Offset(1)))
                .err()
                .unwrap()
                .to_string();
            assert!(
                e.starts_with("serial.direction_gpio_chip = \"gpiochip0\": no GPIO chip"),
                "{e}"
            );
        }
        // Not a GPIO chip at all: a file that is no character device.
        let e = request_line(&gpio("/etc/hostname", GpioLine::Offset(0)))
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("serial.direction_gpio_chip"), "{e}");
    }

    /// The port's last close keeps its modem lines where an inverted RTS transmitter
    /// is used: HUPCL is cleared, through termios2, and the rest of the settings stay.
    #[test]
    fn hupcl_is_cleared_and_nothing_else() {
        use super::super::classic::{get, set, tests::pty};
        use std::os::fd::AsRawFd;
        let (_master, slave) = pty();
        let port = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .open(slave)
            .unwrap();
        let fd = port.as_raw_fd();
        let mut t = get(fd).unwrap();
        t.c_cflag |= libc::HUPCL;
        set(fd, &t).unwrap();
        let before = get(fd).unwrap().c_cflag;
        assert_ne!(before & libc::HUPCL, 0, "the port hangs up on close");
        keep_modem_lines_on_close(fd).unwrap();
        assert_eq!(get(fd).unwrap().c_cflag, before & !libc::HUPCL);
    }
}
