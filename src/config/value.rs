//! What a setting's value may be: the [`Setting`] trait (read from a [`Raw`] and
//! checked, printed as TOML), what a key's value is ([`ValueKind`]) and what it
//! accepts beyond its type ([`Check`]), and the types settings have of their own
//! (`"auto"` or milliseconds, a GPIO line, `host:port`, an address to listen on).

use super::{Raw, ValueError};
use std::net::SocketAddr;

/// What a key's value is, for parsing flags and for messages.
#[derive(Debug, Clone, Copy)]
pub(crate) enum ValueKind {
    Int,
    Bool,
    Str,
    /// An address like 0.0.0.0:502.
    Addr,
    /// One of these words, each with its help.
    Choice(&'static [(&'static str, &'static str)]),
    /// An array, or a table (never a flag's value).
    List,
}

/// What values a key accepts beyond its type.
#[derive(Debug, Clone, Copy)]
pub(crate) enum Check {
    Any,
    /// An inclusive integer range, and how to say it when not "between MIN and MAX".
    Range(i128, i128, Option<&'static str>),
    /// Not blank; the text says what belongs there.
    NonEmpty(&'static str),
    /// One of these words.
    OneOf(&'static [&'static str]),
    /// A path to create a socket at, or empty: its directory must exist (binding there
    /// would fail at start, leaving capture and reload unavailable).
    SocketPath,
    /// An address to listen on, like this example in messages.
    Address(&'static str),
}

impl Check {
    fn int(&self, v: i128) -> Result<(), ValueError> {
        match *self {
            Check::Range(min, max, said) if v < min || v > max => Err(match said {
                Some(said) => format!("must be {said}, got {v}"),
                None => format!("must be between {min} and {max}, got {v}"),
            }
            .into()),
            _ => Ok(()),
        }
    }

    /// The example address messages show.
    fn example(&self) -> &'static str {
        match *self {
            Check::Address(example) => example,
            _ => LISTEN_EXAMPLE,
        }
    }

    fn str(&self, s: &str) -> Result<(), ValueError> {
        match *self {
            Check::NonEmpty(what) if s.trim().is_empty() => {
                Err(format!("must not be empty ({what})").into())
            }
            Check::OneOf(words) if !words.contains(&s) => {
                Err(format!("must be one of {}, got {s:?}", words.join(", ")).into())
            }
            Check::SocketPath if !s.is_empty() => {
                let dir = match std::path::Path::new(s).parent() {
                    Some(d) if !d.as_os_str().is_empty() => d,
                    _ => std::path::Path::new("."),
                };
                if dir.is_dir() {
                    Ok(())
                } else {
                    Err(format!(
                        "the directory {} does not exist (make it, or leave the key empty \
                         under systemd: control.sock in the service's RuntimeDirectory)",
                        dir.display()
                    )
                    .into())
                }
            }
            _ => Ok(()),
        }
    }
}

/// A type a setting can have.
pub(crate) trait Setting: Sized {
    const KIND: ValueKind;
    /// The value `raw` stands for, if it has the right type and passes `check`.
    fn read(raw: &Raw, check: &Check) -> Result<Self, ValueError>;
    /// As written in a TOML file.
    fn print(&self) -> String;
}

/// `types: kind, |raw, check| read, |value| print` implements [`Setting`] for `types`.
macro_rules! setting {
    ($($t:ty),*: $kind:ident, |$raw:ident, $check:ident| $read:expr, |$v:ident| $print:expr) => {$(
        impl Setting for $t {
            const KIND: ValueKind = ValueKind::$kind;
            fn read($raw: &Raw, $check: &Check) -> Result<Self, ValueError> { $read }
            fn print(&self) -> String { let $v = self; $print }
        }
    )*};
}

setting! { u8, u32, u64, usize: Int, |raw, check| match *raw {
    Raw::Int(v) => check.int(v).and(Self::try_from(v).map_err(|_| format!("{v} is too large").into())),
    _ => Err(raw.invalid("an integer")),
}, |v| v.to_string() }
setting! { bool: Bool, |raw, _check| match *raw {
    Raw::Bool(b) => Ok(b),
    _ => Err(raw.invalid("a boolean")),
}, |v| v.to_string() }
setting! { String: Str, |raw, check| match raw {
    Raw::Str(s) => check.str(s).map(|()| s.clone()),
    _ => Err(raw.invalid("a string")),
}, |v| toml::Value::String(v.clone()).to_string() }
setting! { SocketAddr: Addr, |raw, check| match raw {
    Raw::Str(s) => parse_address(s, check.example()),
    _ => Err(raw.invalid(&format!("an address like {}", check.example()))),
}, |v| format!("\"{v}\"") }
setting! { Option<SocketAddr>: Addr, |raw, check| match raw {
    Raw::Str(s) => parse_optional_address(s, check.example()),
    _ => Err(raw.invalid(&format!("an address like {}, or \"\" for none", check.example()))),
}, |v| v.map_or_else(|| "\"\"".to_owned(), |a| format!("\"{a}\"")) }

/// What a Modbus listener's address looks like.
const LISTEN_EXAMPLE: &str = "0.0.0.0:502";
/// What the metrics listener's address looks like (never the Modbus port).
pub(crate) const METRICS_EXAMPLE: &str = "127.0.0.1:9502";

/// `serial.silence_floor_ms`: the least silence that ends a frame, in milliseconds, or
/// `"auto"`, from the port as it is found at each open (`crate::line::port::kind`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Floor {
    /// From the port: none on a pty, the receive FIFO on a native UART, the latency
    /// timer on a USB adapter.
    Auto,
    /// This many milliseconds, whatever the port.
    Ms(u64),
}

impl Setting for Floor {
    const KIND: ValueKind = ValueKind::Str;
    fn read(raw: &Raw, check: &Check) -> Result<Self, ValueError> {
        const EXPECTED: &str = "\"auto\" or a number of milliseconds";
        let ms = match raw {
            Raw::Str(s) if s.trim() == "auto" => return Ok(Floor::Auto),
            Raw::Int(v) => *v,
            // From a flag: the text as typed.
            Raw::Str(s) => s
                .trim()
                .parse::<i128>()
                .map_err(|_| format!("invalid value {s:?}; expected {EXPECTED}"))?,
            _ => return Err(raw.invalid(EXPECTED)),
        };
        check.int(ms)?;
        u64::try_from(ms)
            .map(Floor::Ms)
            .map_err(|_| format!("{ms} is too large").into())
    }
    fn print(&self) -> String {
        match self {
            Floor::Auto => "\"auto\"".into(),
            Floor::Ms(ms) => ms.to_string(),
        }
    }
}

/// `serial.direction_gpio_line`: the GPIO line that switches the transmitter, by its
/// offset on its chip or by its name (docs/rs485.md).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum GpioLine {
    /// Not given: `direction = "gpio"` then refuses the file.
    Unset,
    /// The line at this offset on its chip.
    Offset(u32),
    /// The line of this name (`gpioinfo` lists them).
    Name(String),
}

impl Setting for GpioLine {
    const KIND: ValueKind = ValueKind::Str;
    fn read(raw: &Raw, _check: &Check) -> Result<Self, ValueError> {
        const EXPECTED: &str = "a line offset like 17 or a line name like \"GPIO17\"";
        let offset = |v: i128| {
            u32::try_from(v)
                .map(GpioLine::Offset)
                .map_err(|_| format!("{v} is no line offset; expected {EXPECTED}").into())
        };
        match raw {
            Raw::Int(v) => offset(*v),
            Raw::Str(s) if s.trim().is_empty() => Ok(GpioLine::Unset),
            // From a flag, an offset is typed as text.
            Raw::Str(s) => match s.trim().parse::<i128>() {
                Ok(v) => offset(v),
                Err(_) => Ok(GpioLine::Name(s.trim().to_owned())),
            },
            _ => Err(raw.invalid(EXPECTED)),
        }
    }
    fn print(&self) -> String {
        match self {
            GpioLine::Unset => "\"\"".into(),
            GpioLine::Offset(n) => n.to_string(),
            GpioLine::Name(s) => toml::Value::String(s.clone()).to_string(),
        }
    }
}

/// `host:port` of a device or a slave, the port a number: resolved when connecting,
/// so a name works too; "": not given.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct HostPort(pub(crate) String);

impl Setting for HostPort {
    const KIND: ValueKind = ValueKind::Str;
    fn read(raw: &Raw, check: &Check) -> Result<Self, ValueError> {
        let s = String::read(raw, check)?;
        let ok = s.rsplit_once(':').is_some_and(|(host, port)| {
            !host.trim().is_empty() && port.parse::<u16>().is_ok_and(|p| p > 0)
        });
        match ok {
            true => Ok(Self(s)),
            false => Err(format!("expected host:port, like 192.168.1.20:502, got {s:?}").into()),
        }
    }
    fn print(&self) -> String {
        self.0.print()
    }
}

/// Parses a `tcp.listen` / `--listen` value.
pub(crate) fn parse_listen(s: &str) -> Result<SocketAddr, ValueError> {
    parse_address(s, LISTEN_EXAMPLE)
}

/// Parses an address to listen on, `example` showing what one looks like. A host
/// name is refused with what to give instead: listening needs one of this machine's
/// addresses, and a name could stand for several, or for another machine's.
pub(crate) fn parse_address(s: &str, example: &str) -> Result<SocketAddr, ValueError> {
    s.trim().parse().map_err(|_| {
        let mut m = format!("expected an address like {example}, got {s:?}");
        let named = s.trim().rsplit_once(':').is_some_and(|(host, port)| {
            port.parse::<u16>().is_ok()
                && host.starts_with(|c: char| c.is_ascii_alphabetic())
                && host.parse::<std::net::IpAddr>().is_err()
        });
        if named {
            m += ": a host name is not looked up here; give an IP address of this machine \
                  (127.0.0.1 for this machine only, 0.0.0.0 for every interface)";
        }
        ValueError::new(m)
    })
}

/// [`parse_address`], or none for `""`.
pub(crate) fn parse_optional_address(
    s: &str,
    example: &str,
) -> Result<Option<SocketAddr>, ValueError> {
    if s.trim().is_empty() {
        return Ok(None);
    }
    parse_address(s, example).map(Some)
}
