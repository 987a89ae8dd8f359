//! What a port is, learnt at each open (docs/reliability.md "Knowing the wire"): a
//! pseudo-terminal (no wire: nothing takes time to cross it), a native UART (its
//! driver, its receive FIFO's trigger level), a USB adapter (its driver, its latency
//! timer), TCP, or an in-memory pipe; whether the driver's low latency was turned on;
//! and, from these, whether the rules that read the clock against `baud_rate` apply
//! (`wire`), the silence that ends a frame by default (`silence`), and how long
//! bytes take on the wire (`wire_time`).
//!
//! Plain data: a serial port is found out by `port/serial/detect.rs`; the other ports
//! say what they are.

use crate::config::{Floor, Parity, PortKind, SerialConfig};
use std::fmt;
use std::time::Duration;

/// What carries a line's bytes: a pty, a UART, a USB adapter, TCP or memory (what
/// `port_kind = "auto"` finds at each open).
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Medium {
    /// A pseudo-terminal: bytes cross at once whatever `baud_rate` says.
    Pty,
    /// A UART of the machine's own (ttyS*, ttyAMA*): its driver, and how many bytes
    /// its receive FIFO gathers before it hands them over (`rx_trig_bytes`).
    Uart {
        /// The driver that owns it (`serial8250`, `uart-pl011`...).
        driver: Option<String>,
        /// Bytes its receive FIFO gathers before handing them over.
        trigger: Option<u32>,
    },
    /// A USB serial adapter (ttyUSB*, ttyACM*): its driver, and the latency timer it
    /// hands bytes over by, in milliseconds, when known (FTDI: sysfs `latency_timer`,
    /// or 1 with low latency on).
    Usb {
        /// The driver (`ftdi_sio`, `cp210x`, `cdc_acm`...).
        driver: Option<String>,
        /// Its latency timer in milliseconds, as in effect.
        latency_ms: Option<u32>,
    },
    /// A TCP connection to a device server.
    Tcp,
    /// An in-memory pipe (the in-process tests).
    Memory,
    /// A tty of no kind mbgate knows (a Bluetooth or virtual port): a wire, the old
    /// floor.
    Other {
        /// The driver, if sysfs told.
        driver: Option<String>,
    },
}

/// What became of the low latency asked for (`serial.low_latency`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum LowLatency {
    /// The driver took it (read back with TIOCGSERIAL).
    On,
    /// `serial.low_latency = false`.
    NotAsked,
    /// The driver has no such setting (a pty), or did not keep it.
    Unsupported,
    /// The driver refused it: why.
    Refused(String),
    /// Not a tty.
    NotApplicable,
}

/// A port as found at one open.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct PortInfo {
    /// What it is.
    pub(crate) medium: Medium,
    /// What became of the low latency asked for.
    pub(crate) low_latency: LowLatency,
}

impl PortInfo {
    /// A port with no tty behind it (TCP, the in-memory pipe).
    pub(crate) fn plain(medium: Medium) -> PortInfo {
        PortInfo {
            medium,
            low_latency: LowLatency::NotApplicable,
        }
    }

    /// Before the first open: a wire, the conservative floor.
    pub(crate) fn unknown() -> PortInfo {
        PortInfo::plain(Medium::Other { driver: None })
    }
}

impl Medium {
    /// Is there a wire, whose bytes take their time at `baud_rate`, between the port
    /// and the device? Not on a pty, nor in memory (TCP has its own rules: no wire
    /// time, whole frames).
    pub(crate) fn has_wire(&self) -> bool {
        !matches!(self, Medium::Pty | Medium::Memory | Medium::Tcp)
    }

    /// The least silence that ends a frame, from the port (`silence_floor_ms =
    /// "auto"`), for characters of `char_time` on the line: the longest gap the
    /// receive path can put inside a frame the device sent back to back, with a
    /// margin.
    ///
    /// - pty, pipe: none (3.5 character times then end a frame).
    /// - native UART: 3.5 characters, plus what its FIFO holds back: bytes come over
    ///   when `trigger` have gathered, the last few 4 character times after the last
    ///   one (the FIFO's timeout), so a frame can show a gap of `trigger` + 3
    ///   characters; plus 1 ms for the kernel's deferred hand-over to the reader. An
    ///   unknown trigger counts as 16 (the deepest usual: a 32-byte PL011 half full).
    /// - USB adapter: its latency timer (16 ms unknown, an FTDI's default) plus 2 ms
    ///   (the USB frame, a character or two): 3 ms at 1 ms, 18 ms at 16.
    /// - any other port, TCP (an RTU reply of unknown shape over a device server):
    ///   20 ms, the floor mbgate used before it knew the port.
    pub(crate) fn auto_floor(&self, char_time: Duration) -> Duration {
        const MS: Duration = Duration::from_millis(1);
        match self {
            Medium::Pty | Medium::Memory => Duration::ZERO,
            Medium::Uart { trigger, .. } => {
                let chars = 3.5 + f64::from(trigger.unwrap_or(16)) + 4.0;
                char_time.mul_f64(chars) + MS
            }
            Medium::Usb { latency_ms, .. } => MS * latency_ms.unwrap_or(16) + 2 * MS,
            Medium::Tcp | Medium::Other { .. } => 20 * MS,
        }
    }
}

/// Do the rules that read the clock against `baud_rate` apply on this port (a reply
/// cannot begin before its request has left; a copy of the request that began sooner
/// is its echo)? `serial.port_kind` says, or the port found at open.
pub(crate) fn wire(cfg: &SerialConfig, info: &PortInfo) -> bool {
    match cfg.port_kind {
        PortKind::Auto => info.medium.has_wire(),
        PortKind::Pty => false,
        PortKind::Wire => true,
    }
}

/// The silence that ends a frame on this port: 3.5 character times, never less than
/// `serial.silence_floor_ms` (a number, or from the port: [`Medium::auto_floor`]).
pub(crate) fn silence(cfg: &SerialConfig, info: &PortInfo) -> Duration {
    let bits = bits_per_char(cfg);
    let t35 = Duration::from_micros(crate::frame::rtu::t35_us(cfg.baud_rate, bits));
    t35.max(floor(cfg, info))
}

/// `serial.silence_floor_ms` for this port.
pub(crate) fn floor(cfg: &SerialConfig, info: &PortInfo) -> Duration {
    match cfg.silence_floor_ms {
        Floor::Ms(ms) => Duration::from_millis(ms),
        Floor::Auto => info.medium.auto_floor(wire_time(cfg, 1000) / 1000),
    }
}

impl fmt::Display for Medium {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let driver = |d: &Option<String>| d.clone().unwrap_or_else(|| "driver unknown".into());
        match self {
            Medium::Pty => f.write_str("a pseudo-terminal (no wire)"),
            Medium::Uart { driver: d, trigger } => {
                write!(f, "a native UART ({}", driver(d))?;
                match trigger {
                    Some(t) => write!(f, ", FIFO trigger {t} bytes)"),
                    None => f.write_str(")"),
                }
            }
            Medium::Usb {
                driver: d,
                latency_ms,
            } => {
                write!(f, "a USB adapter ({}", driver(d))?;
                match latency_ms {
                    Some(ms) => write!(f, ", latency timer {ms} ms)"),
                    None => f.write_str(", latency timer unknown)"),
                }
            }
            Medium::Tcp => f.write_str("TCP"),
            Medium::Memory => f.write_str("an in-memory pipe (no wire)"),
            Medium::Other { driver: d } => write!(f, "a serial port ({})", driver(d)),
        }
    }
}

impl fmt::Display for PortInfo {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.medium)?;
        match &self.low_latency {
            LowLatency::On => f.write_str(", low latency on"),
            LowLatency::NotAsked => {
                f.write_str(", low latency not asked (serial.low_latency = false)")
            }
            LowLatency::Unsupported | LowLatency::NotApplicable => Ok(()),
            LowLatency::Refused(why) => write!(f, ", low latency refused ({why})"),
        }
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

    const MS: Duration = Duration::from_millis(1);

    #[test]
    fn wire_time_at_19200_8n1() {
        let cfg = SerialConfig::default();
        assert_eq!(bits_per_char(&cfg), 10);
        // 12 bytes x 10 bits / 19200 bit/s = 6.25 ms
        assert_eq!(wire_time(&cfg, 12), Duration::from_micros(6250));
    }

    /// The floors of docs/reliability.md: 0 on a pty, 3.5 + trigger + 4 characters
    /// and 1 ms on a UART, the latency timer + 2 ms on a USB adapter (3 ms at 1 ms,
    /// 18 at 16), 20 ms on anything else.
    #[test]
    fn auto_floors_from_the_port() {
        let char_115200 = Duration::from_nanos(86_806);
        assert_eq!(Medium::Pty.auto_floor(char_115200), Duration::ZERO);
        let uart = Medium::Uart {
            driver: None,
            trigger: Some(8),
        };
        let f = uart.auto_floor(char_115200);
        assert!(
            f > Duration::from_micros(2340) && f < Duration::from_micros(2350),
            "{f:?}"
        );
        let usb = |ms| Medium::Usb {
            driver: None,
            latency_ms: ms,
        };
        assert_eq!(usb(Some(1)).auto_floor(char_115200), 3 * MS);
        assert_eq!(usb(Some(16)).auto_floor(char_115200), 18 * MS);
        assert_eq!(usb(None).auto_floor(char_115200), 18 * MS);
        assert_eq!(Medium::Tcp.auto_floor(char_115200), 20 * MS);
        // The resolved silence: never below 3.5 characters, an explicit number wins.
        let cfg = SerialConfig::default();
        let pty = PortInfo::plain(Medium::Pty);
        assert_eq!(silence(&cfg, &pty), Duration::from_micros(1823));
        let cfg = SerialConfig {
            silence_floor_ms: Floor::Ms(5),
            ..SerialConfig::default()
        };
        assert_eq!(silence(&cfg, &pty), 5 * MS);
        assert_eq!(silence(&cfg, &PortInfo::plain(usb(Some(16)))), 5 * MS);
    }

    #[test]
    fn the_declared_kind_wins_over_the_found_one() {
        let mut cfg = SerialConfig::default();
        let pty = PortInfo::plain(Medium::Pty);
        let usb = PortInfo::plain(Medium::Usb {
            driver: None,
            latency_ms: None,
        });
        assert!(!wire(&cfg, &pty));
        assert!(wire(&cfg, &usb));
        cfg.port_kind = PortKind::Wire;
        assert!(wire(&cfg, &pty));
        cfg.port_kind = PortKind::Pty;
        assert!(!wire(&cfg, &usb));
    }
}
