//! The configuration model of design.md §4: every key, its default, and validation.
//!
//! Loading reports errors that name the file, the line and the key (design.md §3:
//! exit code 2 on a bad configuration), e.g.
//! `config/x.toml:7:13: serial.baud_rate: must be between 50 and 4000000, got 10`.
//!
//! - [`load`] / [`parse`] read a file or a string into a [`Config`]. Every range check
//!   happens while deserializing, so each error carries the position of the offending
//!   value and its full key.
//! - [`Overrides`] are the command-line flags that override the file (`mbgate run
//!   --baud 9600 ...`); [`Overrides::apply`] checks the same ranges and names the flag.
//! - [`to_toml`] prints the effective configuration (`mbgate check-config`).

use serde::de::{self, Deserializer, Visitor};
use serde::{Deserialize, Serialize};
use std::fmt;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

/// The whole file (design.md §4). Every section and key is optional; missing ones take
/// the defaults below. Unknown keys are errors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    pub serial: SerialConfig,
    pub tcp: TcpConfig,
    pub relay: RelayConfig,
    pub log: LogConfig,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
#[value(rename_all = "lower")]
pub enum Parity {
    None,
    Even,
    Odd,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
#[value(rename_all = "lower")]
pub enum FlowControl {
    /// RTS/CTS, as the device manual advises.
    Hardware,
    /// XON/XOFF.
    Software,
    None,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
#[value(rename_all = "lower")]
pub enum Framing {
    /// CIE-M10 serial Modbus/TCP: whole MBAP frames on the line (protocol.md §3).
    Mbap,
    /// Modbus RTU: unit, PDU, CRC-16; one transaction at a time.
    Rtu,
    /// Modbus ASCII: `:`, hex, LRC, CR LF; one transaction at a time.
    Ascii,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
#[value(rename_all = "lower")]
pub enum BroadcastReply {
    /// The master gets nothing back (as on the bus).
    None,
    /// The master gets the reply the device would have given (mbusd's replyonbroadcast).
    Echo,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
#[value(rename_all = "lower")]
pub enum Notifications {
    /// Frames from the device that answer no request are dropped and counted.
    Drop,
    /// Well-formed unsolicited frames go to every connected master.
    Broadcast,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SerialConfig {
    #[serde(deserialize_with = "de_key::serial_path")]
    pub path: String,
    #[serde(deserialize_with = "de_key::baud_rate")]
    pub baud_rate: u32,
    /// 7 or 8.
    #[serde(deserialize_with = "de_key::data_bits")]
    pub data_bits: u8,
    pub parity: Parity,
    /// 1 or 2.
    #[serde(deserialize_with = "de_key::stop_bits")]
    pub stop_bits: u8,
    pub flow_control: FlowControl,
    pub framing: Framing,
    /// The least silence that ends a frame, whatever 3.5 character times come to: a
    /// USB adapter delivers bytes in bursts its latency timer apart (FTDI: 16 ms).
    /// RTU: it ends a reply of unknown shape. MBAP: it confirms a reply with nothing
    /// after it, and a frame whose bytes straddle it is suspect (docs/reliability.md).
    #[serde(deserialize_with = "de_key::silence_floor_ms")]
    pub silence_floor_ms: u64,
    /// Turn on the kernel's RS-485 mode (TIOCSRS485): RTS drives the transmitter.
    pub rs485: bool,
    #[serde(deserialize_with = "de_key::rs485_delay_ms")]
    pub rs485_delay_before_send_ms: u32,
    #[serde(deserialize_with = "de_key::rs485_delay_ms")]
    pub rs485_delay_after_send_ms: u32,
    /// The adapter echoes what is sent: read it back and discard it.
    pub echo: bool,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TcpConfig {
    #[serde(deserialize_with = "de_key::listen")]
    pub listen: SocketAddr,
    #[serde(deserialize_with = "de_key::max_connections")]
    pub max_connections: usize,
    /// 0 = never close idle masters.
    #[serde(deserialize_with = "de_key::idle_timeout_ms")]
    pub idle_timeout_ms: u64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RelayConfig {
    #[serde(deserialize_with = "de_key::response_timeout_ms")]
    pub response_timeout_ms: u64,
    /// A partial frame that gets no byte for this long is discarded. MBAP: a reply
    /// with nothing after it, while other replies are due, is taken after this much
    /// quiet (a shorter pause may sit inside the next reply).
    #[serde(deserialize_with = "de_key::frame_gap_ms")]
    pub frame_gap_ms: u64,
    #[serde(deserialize_with = "de_key::max_in_flight")]
    pub max_in_flight: usize,
    #[serde(deserialize_with = "de_key::max_pending_per_connection")]
    pub max_pending_per_connection: usize,
    #[serde(deserialize_with = "de_key::queue_depth")]
    pub queue_depth: usize,
    #[serde(deserialize_with = "de_key::retries")]
    pub retries: u32,
    pub retry_writes: bool,
    pub notifications: Notifications,
    /// RTU/ASCII: the line stays quiet this long after a broadcast (unit 0).
    #[serde(deserialize_with = "de_key::broadcast_delay_ms")]
    pub broadcast_delay_ms: u64,
    pub broadcast_reply: BroadcastReply,
    /// RTU/ASCII: back off a unit that timed out `unit_backoff_after` times in a row.
    pub unit_backoff: bool,
    #[serde(deserialize_with = "de_key::unit_backoff_after")]
    pub unit_backoff_after: u32,
    #[serde(deserialize_with = "de_key::unit_backoff_ms")]
    pub unit_backoff_ms: u64,
    #[serde(deserialize_with = "de_key::unit_backoff_ms")]
    pub unit_backoff_max_ms: u64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LogConfig {
    /// One of [`LOG_LEVELS`].
    #[serde(deserialize_with = "de_key::log_level")]
    pub level: String,
    pub traffic: bool,
}

impl Default for SerialConfig {
    fn default() -> Self {
        Self {
            path: "/dev/ttyUSB0".into(),
            baud_rate: 19200,
            data_bits: 8,
            parity: Parity::None,
            stop_bits: 1,
            flow_control: FlowControl::Hardware,
            framing: Framing::Mbap,
            silence_floor_ms: 20,
            rs485: false,
            rs485_delay_before_send_ms: 0,
            rs485_delay_after_send_ms: 0,
            echo: false,
        }
    }
}

impl Default for TcpConfig {
    fn default() -> Self {
        Self {
            listen: "0.0.0.0:502".parse().expect("valid literal"),
            max_connections: 32,
            idle_timeout_ms: 60_000,
        }
    }
}

impl Default for RelayConfig {
    fn default() -> Self {
        Self {
            response_timeout_ms: 1000,
            frame_gap_ms: 50,
            max_in_flight: 1,
            max_pending_per_connection: 16,
            queue_depth: 64,
            retries: 0,
            retry_writes: false,
            notifications: Notifications::Drop,
            broadcast_delay_ms: 100,
            broadcast_reply: BroadcastReply::None,
            unit_backoff: true,
            unit_backoff_after: 3,
            unit_backoff_ms: 1000,
            unit_backoff_max_ms: 30_000,
        }
    }
}

impl RelayConfig {
    /// The longest the relay takes to answer a request that is on the line: the
    /// response timeout of every attempt (design.md §1 step 5).
    pub fn answer_within(&self) -> std::time::Duration {
        std::time::Duration::from_millis(self.response_timeout_ms * u64::from(self.retries + 1))
    }
}

impl Default for LogConfig {
    fn default() -> Self {
        Self {
            level: "info".into(),
            traffic: false,
        }
    }
}

#[allow(clippy::derivable_impls)]
impl Default for Config {
    fn default() -> Self {
        Self {
            serial: SerialConfig::default(),
            tcp: TcpConfig::default(),
            relay: RelayConfig::default(),
            log: LogConfig::default(),
        }
    }
}

// ---------------------------------------------------------------------------------------
// Errors
// ---------------------------------------------------------------------------------------

/// Why a configuration was rejected. The `Display` text is the whole message for the
/// operator: it names the file, the line and column, and the key (or the flag).
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read (missing, permissions, not UTF-8...).
    #[error("{}: cannot read the configuration file: {source}", path.display())]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    /// The text is not valid TOML. `key` is the key on the offending line when it can
    /// be told.
    #[error("{origin}:{line}:{column}: {}TOML syntax error: {message}", key_prefix(.key))]
    Syntax {
        origin: String,
        line: usize,
        column: usize,
        key: Option<String>,
        message: String,
    },
    /// Valid TOML, but a key is unknown, has the wrong type or an out-of-range value.
    /// `key` is the full dotted key (`serial.baud_rate`); `line`/`column` (1-based) point
    /// at the value, or at the key for an unknown key.
    #[error("{origin}:{}{key}: {message}", position(.line, .column))]
    Invalid {
        origin: String,
        line: Option<usize>,
        column: Option<usize>,
        key: String,
        message: String,
    },
    /// A command-line override is out of range; `flag` is e.g. `--baud`.
    #[error("{flag}: {message}")]
    Override { flag: String, message: String },
}

fn key_prefix(key: &Option<String>) -> String {
    key.as_ref().map(|k| format!("{k}: ")).unwrap_or_default()
}

fn position(line: &Option<usize>, column: &Option<usize>) -> String {
    match (line, column) {
        (Some(l), Some(c)) => format!("{l}:{c}: "),
        (Some(l), None) => format!("{l}: "),
        _ => " ".into(),
    }
}

// ---------------------------------------------------------------------------------------
// Loading
// ---------------------------------------------------------------------------------------

/// Read and validate the configuration file at `path`. Error messages use `path` as
/// given (relative paths stay relative).
pub fn load(path: &Path) -> Result<Config, ConfigError> {
    let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    parse(&text, &path.display().to_string())
}

/// Parse and validate configuration text. `origin` names the text in error messages
/// (normally the file name).
pub fn parse(text: &str, origin: &str) -> Result<Config, ConfigError> {
    let de = toml::Deserializer::parse(text).map_err(|e| syntax_error(text, origin, &e))?;
    serde_path_to_error::deserialize(de).map_err(|e| {
        let key = e.path().to_string();
        invalid_error(text, origin, key, e.inner())
    })
}

fn syntax_error(text: &str, origin: &str, err: &toml::de::Error) -> ConfigError {
    let (line, column) = err
        .span()
        .map(|s| line_col(text, s.start))
        .unwrap_or((1, 1));
    ConfigError::Syntax {
        origin: origin.to_owned(),
        line,
        column,
        key: key_on_line(text, line),
        message: one_line(err.message()),
    }
}

fn invalid_error(text: &str, origin: &str, mut key: String, err: &toml::de::Error) -> ConfigError {
    let raw = one_line(err.message());
    let message = if let Some((field, expected)) = parse_serde_unknown(&raw, "unknown field `") {
        // serde_path_to_error normally already ends the path with the unknown key.
        if key == "." {
            key = field.clone();
        } else if !key.ends_with(&format!(".{field}")) && key != field {
            key = format!("{key}.{field}");
        }
        let mut m = format!("unknown key; expected one of {}", expected.join(", "));
        if let Some(s) = suggest(&field, &expected) {
            m.push_str(&format!(" (did you mean `{s}`?)"));
        }
        m
    } else if let Some((value, expected)) = parse_serde_unknown(&raw, "unknown variant `") {
        format!(
            "invalid value {value:?}; expected one of {}",
            expected.join(", ")
        )
    } else if raw == "wanted string or table" {
        // toml's words for a non-string where an enum value belongs.
        match allowed_values(&key) {
            Some(values) => format!("expected a string, one of {}", values.join(", ")),
            None => "expected a string".into(),
        }
    } else if let Some(at) = raw.find(", expected struct ") {
        format!("{}, expected a table ([section])", &raw[..at])
    } else {
        raw
    };
    let (line, column) = match err.span() {
        Some(s) => {
            let (l, c) = line_col(text, s.start);
            (Some(l), Some(c))
        }
        None => (None, None),
    };
    ConfigError::Invalid {
        origin: origin.to_owned(),
        line,
        column,
        key,
        message,
    }
}

fn one_line(s: &str) -> String {
    s.trim().replace('\n', "; ")
}

/// 1-based line and column (in characters) of byte `offset` in `text`.
fn line_col(text: &str, offset: usize) -> (usize, usize) {
    let mut offset = offset.min(text.len());
    while !text.is_char_boundary(offset) {
        offset -= 1;
    }
    let before = &text[..offset];
    let line = before.matches('\n').count() + 1;
    let line_start = before.rfind('\n').map_or(0, |i| i + 1);
    (line, before[line_start..].chars().count() + 1)
}

/// The values an enum-valued key accepts, by full key.
fn allowed_values(key: &str) -> Option<Vec<String>> {
    fn names<T: clap::ValueEnum>() -> Vec<String> {
        T::value_variants()
            .iter()
            .filter_map(|v| v.to_possible_value())
            .map(|v| v.get_name().to_owned())
            .collect()
    }
    Some(match key {
        "serial.parity" => names::<Parity>(),
        "serial.flow_control" => names::<FlowControl>(),
        "serial.framing" => names::<Framing>(),
        "relay.notifications" => names::<Notifications>(),
        "relay.broadcast_reply" => names::<BroadcastReply>(),
        _ => return None,
    })
}

/// Splits serde's "unknown field `x`, expected one of `a`, `b`" (or "unknown variant")
/// into `x` and `[a, b]`.
fn parse_serde_unknown(msg: &str, prefix: &str) -> Option<(String, Vec<String>)> {
    let rest = msg.strip_prefix(prefix)?;
    let end = rest.find('`')?;
    let name = rest[..end].to_owned();
    let expected = rest[end + 1..]
        .split('`')
        .skip(1)
        .step_by(2)
        .map(str::to_owned)
        .collect();
    Some((name, expected))
}

/// The expected name closest to a misspelt `name`, if one is close enough.
fn suggest<'a>(name: &str, expected: &'a [String]) -> Option<&'a str> {
    let norm = |s: &str| -> String {
        s.chars()
            .filter(|c| *c != '_' && *c != '-')
            .flat_map(char::to_lowercase)
            .collect()
    };
    let n = norm(name);
    expected
        .iter()
        .map(|e| (strsim::levenshtein(&n, &norm(e)), e))
        .filter(|(d, e)| *d <= 2.max(e.len() / 4))
        .min_by_key(|(d, _)| *d)
        .map(|(_, e)| e.as_str())
}

/// Best-effort name of the key on a line that failed to parse: `section.key` for a
/// `key = ...` line, `section` for a `[section]` header. `None` when unclear.
fn key_on_line(text: &str, line: usize) -> Option<String> {
    fn bare(s: &str) -> bool {
        !s.is_empty()
            && s.chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.'))
    }
    fn header(l: &str) -> Option<&str> {
        let t = l.trim();
        let inner = t.strip_prefix('[')?;
        if inner.starts_with('[') {
            return None;
        }
        let name = inner[..inner.find(']')?].trim();
        bare(name).then_some(name)
    }
    let lines: Vec<&str> = text.split('\n').collect();
    let current = lines.get(line.checked_sub(1)?)?;
    if current.trim_start().starts_with('[') {
        return header(current).map(str::to_owned);
    }
    let section = lines[..line - 1].iter().rev().find_map(|l| header(l));
    let key = current[..current.find('=')?].trim();
    if !bare(key) {
        return None;
    }
    Some(match section {
        Some(s) => format!("{s}.{key}"),
        None => key.to_owned(),
    })
}

// ---------------------------------------------------------------------------------------
// Validation rules, shared by the file and the command line
// ---------------------------------------------------------------------------------------

/// The values `log.level` accepts.
pub const LOG_LEVELS: [&str; 5] = ["trace", "debug", "info", "warn", "error"];

/// An inclusive integer range a key must lie in.
#[derive(Debug, Clone, Copy)]
struct Limit {
    min: i128,
    max: i128,
    /// Replaces "must be between min and max".
    text: Option<&'static str>,
}

impl Limit {
    const fn range(min: i128, max: i128) -> Self {
        Self {
            min,
            max,
            text: None,
        }
    }

    fn check<T: TryFrom<i128>>(self, v: i128) -> Result<T, String> {
        if v < self.min || v > self.max {
            return Err(match self.text {
                Some(text) => format!("{text}, got {v}"),
                None => format!("must be between {} and {}, got {v}", self.min, self.max),
            });
        }
        T::try_from(v).map_err(|_| format!("{v} is too large"))
    }
}

const BAUD_RATE: Limit = Limit::range(50, 4_000_000);
const DATA_BITS: Limit = Limit {
    min: 7,
    max: 8,
    text: Some("must be 7 or 8"),
};
const STOP_BITS: Limit = Limit {
    min: 1,
    max: 2,
    text: Some("must be 1 or 2"),
};
const MAX_CONNECTIONS: Limit = Limit::range(1, 4096);
const IDLE_TIMEOUT_MS: Limit = Limit {
    min: 0,
    max: u64::MAX as i128,
    text: Some("must be 0 (never) or a number of milliseconds"),
};
const RESPONSE_TIMEOUT_MS: Limit = Limit::range(1, 600_000);
const FRAME_GAP_MS: Limit = Limit::range(1, 60_000);
const MAX_IN_FLIGHT: Limit = Limit::range(1, 255);
const MAX_PENDING_PER_CONNECTION: Limit = Limit::range(1, 1024);
const QUEUE_DEPTH: Limit = Limit::range(1, 65_536);
const RETRIES: Limit = Limit::range(0, 10);
const SILENCE_FLOOR_MS: Limit = Limit::range(0, 1000);
const RS485_DELAY_MS: Limit = Limit::range(0, 1000);
const BROADCAST_DELAY_MS: Limit = Limit::range(0, 60_000);
const UNIT_BACKOFF_AFTER: Limit = Limit::range(1, 100);
const UNIT_BACKOFF_MS: Limit = Limit::range(1, 3_600_000);

fn check_serial_path(path: &str) -> Result<(), String> {
    if path.trim().is_empty() {
        Err("must not be empty (the serial device, e.g. /dev/ttyUSB0)".into())
    } else {
        Ok(())
    }
}

const LISTEN_EXPECTED: &str = "an address like 0.0.0.0:502";

/// Parses a `tcp.listen` / `--listen` value.
fn parse_listen(s: &str) -> Result<SocketAddr, String> {
    s.trim()
        .parse()
        .map_err(|_| format!("expected {LISTEN_EXPECTED}, got {s:?}"))
}

fn check_log_level(level: &str) -> Result<(), String> {
    if LOG_LEVELS.contains(&level) {
        Ok(())
    } else {
        Err(format!(
            "must be one of {}, got {level:?}",
            LOG_LEVELS.join(", ")
        ))
    }
}

/// `deserialize_with` helpers: each validates while deserializing, so a bad value
/// gets the position of the value in the file.
mod de_key {
    use super::*;

    /// Any TOML integer, widened so that range errors (not "invalid value: integer
    /// `-1`, expected u32") are what the user sees.
    struct Int;

    impl Visitor<'_> for Int {
        type Value = i128;

        fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
            f.write_str("an integer")
        }

        fn visit_i64<E: de::Error>(self, v: i64) -> Result<i128, E> {
            Ok(v.into())
        }

        fn visit_u64<E: de::Error>(self, v: u64) -> Result<i128, E> {
            Ok(v.into())
        }

        fn visit_i128<E: de::Error>(self, v: i128) -> Result<i128, E> {
            Ok(v)
        }

        fn visit_u128<E: de::Error>(self, v: u128) -> Result<i128, E> {
            Ok(i128::try_from(v).unwrap_or(i128::MAX))
        }
    }

    macro_rules! int_keys {
        ($($name:ident: $ty:ty = $limit:expr;)*) => {$(
            pub(super) fn $name<'de, D: Deserializer<'de>>(d: D) -> Result<$ty, D::Error> {
                let v = d.deserialize_i64(Int)?;
                $limit.check(v).map_err(de::Error::custom)
            }
        )*};
    }

    int_keys! {
        baud_rate: u32 = BAUD_RATE;
        data_bits: u8 = DATA_BITS;
        stop_bits: u8 = STOP_BITS;
        max_connections: usize = MAX_CONNECTIONS;
        idle_timeout_ms: u64 = IDLE_TIMEOUT_MS;
        response_timeout_ms: u64 = RESPONSE_TIMEOUT_MS;
        frame_gap_ms: u64 = FRAME_GAP_MS;
        max_in_flight: usize = MAX_IN_FLIGHT;
        max_pending_per_connection: usize = MAX_PENDING_PER_CONNECTION;
        queue_depth: usize = QUEUE_DEPTH;
        retries: u32 = RETRIES;
        silence_floor_ms: u64 = SILENCE_FLOOR_MS;
        rs485_delay_ms: u32 = RS485_DELAY_MS;
        broadcast_delay_ms: u64 = BROADCAST_DELAY_MS;
        unit_backoff_after: u32 = UNIT_BACKOFF_AFTER;
        unit_backoff_ms: u64 = UNIT_BACKOFF_MS;
    }

    pub(super) fn serial_path<'de, D: Deserializer<'de>>(d: D) -> Result<String, D::Error> {
        let s = String::deserialize(d)?;
        check_serial_path(&s).map_err(de::Error::custom)?;
        Ok(s)
    }

    pub(super) fn log_level<'de, D: Deserializer<'de>>(d: D) -> Result<String, D::Error> {
        let s = String::deserialize(d)?;
        check_log_level(&s).map_err(de::Error::custom)?;
        Ok(s)
    }

    struct Listen;

    impl Visitor<'_> for Listen {
        type Value = SocketAddr;

        fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
            f.write_str(LISTEN_EXPECTED)
        }

        fn visit_str<E: de::Error>(self, v: &str) -> Result<SocketAddr, E> {
            parse_listen(v).map_err(E::custom)
        }
    }

    pub(super) fn listen<'de, D: Deserializer<'de>>(d: D) -> Result<SocketAddr, D::Error> {
        d.deserialize_str(Listen)
    }
}

// ---------------------------------------------------------------------------------------
// Command-line overrides
// ---------------------------------------------------------------------------------------

/// Flags that override the configuration file (design.md §3: `mbgate run --serial PATH
/// --listen ADDR [--baud N] ...`). Flatten into a subcommand with
/// `#[command(flatten)] overrides: Overrides`, then call [`Overrides::apply`] on the
/// loaded (or default) configuration.
#[derive(Debug, Clone, Default, PartialEq, Eq, clap::Args)]
// `about = None`: this doc comment is for rustdoc, not for the --help of whatever
// subcommand flattens these flags.
// No help heading here either: it would leak onto arguments declared after the
// flatten. Use `#[command(flatten, next_help_heading = "...")]` on the field if wanted.
#[command(about = None, long_about = None)]
pub struct Overrides {
    /// Serial device of the Modbus device [serial.path]
    #[arg(long = "serial", value_name = "PATH")]
    pub serial: Option<String>,
    /// TCP address to listen on for Modbus/TCP masters, e.g. 0.0.0.0:502 [tcp.listen]
    #[arg(long, value_name = "ADDR", value_parser = parse_listen)]
    pub listen: Option<SocketAddr>,
    /// Serial speed in bit/s, 50..=4000000 [serial.baud_rate]
    #[arg(long, value_name = "N")]
    pub baud: Option<u32>,
    /// Data bits, 7 or 8 [serial.data_bits]
    #[arg(long, value_name = "N")]
    pub data_bits: Option<u8>,
    /// Parity [serial.parity]
    #[arg(long, value_enum)]
    pub parity: Option<Parity>,
    /// Stop bits, 1 or 2 [serial.stop_bits]
    #[arg(long, value_name = "N")]
    pub stop_bits: Option<u8>,
    /// Serial flow control [serial.flow_control]
    #[arg(long, value_enum)]
    pub flow_control: Option<FlowControl>,
    /// Serial framing [serial.framing]
    #[arg(long, value_enum)]
    pub framing: Option<Framing>,
    /// Least silence that ends a frame (above the adapter's latency timer), 0..=1000
    /// ms [serial.silence_floor_ms]
    #[arg(long, value_name = "MS")]
    pub silence_floor_ms: Option<u64>,
    /// Turn on the kernel's RS-485 mode (TIOCSRS485) [serial.rs485]
    #[arg(
        long,
        value_name = "BOOL",
        num_args = 0..=1,
        require_equals = true,
        default_missing_value = "true"
    )]
    pub rs485: Option<bool>,
    /// RS-485: RTS delay before sending, 0..=1000 ms [serial.rs485_delay_before_send_ms]
    #[arg(long, value_name = "MS")]
    pub rs485_delay_before_send_ms: Option<u32>,
    /// RS-485: RTS delay after sending, 0..=1000 ms [serial.rs485_delay_after_send_ms]
    #[arg(long, value_name = "MS")]
    pub rs485_delay_after_send_ms: Option<u32>,
    /// The adapter echoes what is sent: read it back and discard it [serial.echo]
    #[arg(
        long,
        value_name = "BOOL",
        num_args = 0..=1,
        require_equals = true,
        default_missing_value = "true"
    )]
    pub echo: Option<bool>,
    /// Time to wait for the device's reply, 1..=600000 ms [relay.response_timeout_ms]
    #[arg(long, value_name = "MS")]
    pub response_timeout_ms: Option<u64>,
    /// Silence after which a partial serial frame is discarded (MBAP: and a held
    /// reply taken while other replies are due), 1..=60000 ms [relay.frame_gap_ms]
    #[arg(long, value_name = "MS")]
    pub frame_gap_ms: Option<u64>,
    /// Requests outstanding on the serial line at once, 1..=255 [relay.max_in_flight]
    #[arg(long, value_name = "N")]
    pub max_in_flight: Option<usize>,
    /// Queued requests per master connection, 1..=1024 [relay.max_pending_per_connection]
    #[arg(long, value_name = "N")]
    pub max_pending_per_connection: Option<usize>,
    /// Total queued requests, 1..=65536 [relay.queue_depth]
    #[arg(long, value_name = "N")]
    pub queue_depth: Option<usize>,
    /// Simultaneous master connections, 1..=4096 [tcp.max_connections]
    #[arg(long, value_name = "N")]
    pub max_connections: Option<usize>,
    /// Close a master connection idle this long, 0 = never [tcp.idle_timeout_ms]
    #[arg(long, value_name = "MS")]
    pub idle_timeout_ms: Option<u64>,
    /// Resends after a timeout (reads only unless --retry-writes), 0..=10 [relay.retries]
    #[arg(long, value_name = "N")]
    pub retries: Option<u32>,
    /// Also resend writes after a timeout (a resent write may act twice)
    /// [relay.retry_writes]
    #[arg(
        long,
        value_name = "BOOL",
        num_args = 0..=1,
        require_equals = true,
        default_missing_value = "true"
    )]
    pub retry_writes: Option<bool>,
    /// What to do with device frames that answer no request [relay.notifications]
    #[arg(long, value_enum)]
    pub notifications: Option<Notifications>,
    /// RTU/ASCII: quiet time after a broadcast (unit 0), 0..=60000 ms
    /// [relay.broadcast_delay_ms]
    #[arg(long, value_name = "MS")]
    pub broadcast_delay_ms: Option<u64>,
    /// RTU/ASCII: what a master gets for a broadcast [relay.broadcast_reply]
    #[arg(long, value_enum)]
    pub broadcast_reply: Option<BroadcastReply>,
    /// RTU/ASCII: back off units that keep timing out [relay.unit_backoff]
    #[arg(
        long,
        value_name = "BOOL",
        num_args = 0..=1,
        require_equals = true,
        default_missing_value = "true"
    )]
    pub unit_backoff: Option<bool>,
    /// Timeouts in a row that back a unit off, 1..=100 [relay.unit_backoff_after]
    #[arg(long, value_name = "N")]
    pub unit_backoff_after: Option<u32>,
    /// First back-off interval, 1..=3600000 ms [relay.unit_backoff_ms]
    #[arg(long, value_name = "MS")]
    pub unit_backoff_ms: Option<u64>,
    /// Longest back-off interval, 1..=3600000 ms [relay.unit_backoff_max_ms]
    #[arg(long, value_name = "MS")]
    pub unit_backoff_max_ms: Option<u64>,
    /// Log level [log.level]
    #[arg(long, value_name = "LEVEL", value_parser = LOG_LEVELS)]
    pub log_level: Option<String>,
    /// Log every frame, both directions, as hex at debug level [log.traffic]
    #[arg(
        long,
        value_name = "BOOL",
        num_args = 0..=1,
        require_equals = true,
        default_missing_value = "true"
    )]
    pub traffic: Option<bool>,
}

impl Overrides {
    /// Apply every flag that was given to `cfg`, checking the same ranges as the file.
    /// On error `cfg` is left unchanged and the message names the flag.
    pub fn apply(&self, cfg: &mut Config) -> Result<(), ConfigError> {
        fn bad(flag: &str, message: String) -> ConfigError {
            ConfigError::Override {
                flag: flag.to_owned(),
                message,
            }
        }
        fn int<T: TryInto<i128>, U: TryFrom<i128>>(
            flag: &str,
            v: T,
            limit: Limit,
        ) -> Result<U, ConfigError> {
            let v: i128 = v
                .try_into()
                .map_err(|_| bad(flag, "value is too large".into()))?;
            limit.check(v).map_err(|m| bad(flag, m))
        }

        let mut c = cfg.clone();
        if let Some(path) = &self.serial {
            check_serial_path(path).map_err(|m| bad("--serial", m))?;
            c.serial.path = path.clone();
        }
        // A flag given replaces the key as it is; a number is checked against the
        // key's range first, and the error names the flag.
        macro_rules! set {
            ($($section:ident.$key:ident = $flag:ident;)*) => {
                $(if let Some(v) = self.$flag {
                    c.$section.$key = v;
                })*
            };
        }
        macro_rules! set_checked {
            ($($section:ident.$key:ident = $flag:ident, $name:literal, $limit:ident;)*) => {
                $(if let Some(v) = self.$flag {
                    c.$section.$key = int($name, v, $limit)?;
                })*
            };
        }
        set! {
            tcp.listen = listen;
            serial.parity = parity;
            serial.flow_control = flow_control;
            serial.framing = framing;
            serial.rs485 = rs485;
            serial.echo = echo;
            relay.retry_writes = retry_writes;
            relay.notifications = notifications;
            relay.broadcast_reply = broadcast_reply;
            relay.unit_backoff = unit_backoff;
            log.traffic = traffic;
        }
        set_checked! {
            serial.baud_rate = baud, "--baud", BAUD_RATE;
            serial.data_bits = data_bits, "--data-bits", DATA_BITS;
            serial.stop_bits = stop_bits, "--stop-bits", STOP_BITS;
            serial.silence_floor_ms = silence_floor_ms, "--silence-floor-ms", SILENCE_FLOOR_MS;
            serial.rs485_delay_before_send_ms = rs485_delay_before_send_ms, "--rs485-delay-before-send-ms", RS485_DELAY_MS;
            serial.rs485_delay_after_send_ms = rs485_delay_after_send_ms, "--rs485-delay-after-send-ms", RS485_DELAY_MS;
            relay.response_timeout_ms = response_timeout_ms, "--response-timeout-ms", RESPONSE_TIMEOUT_MS;
            relay.frame_gap_ms = frame_gap_ms, "--frame-gap-ms", FRAME_GAP_MS;
            relay.max_in_flight = max_in_flight, "--max-in-flight", MAX_IN_FLIGHT;
            relay.max_pending_per_connection = max_pending_per_connection, "--max-pending-per-connection", MAX_PENDING_PER_CONNECTION;
            relay.queue_depth = queue_depth, "--queue-depth", QUEUE_DEPTH;
            tcp.max_connections = max_connections, "--max-connections", MAX_CONNECTIONS;
            tcp.idle_timeout_ms = idle_timeout_ms, "--idle-timeout-ms", IDLE_TIMEOUT_MS;
            relay.retries = retries, "--retries", RETRIES;
            relay.broadcast_delay_ms = broadcast_delay_ms, "--broadcast-delay-ms", BROADCAST_DELAY_MS;
            relay.unit_backoff_after = unit_backoff_after, "--unit-backoff-after", UNIT_BACKOFF_AFTER;
            relay.unit_backoff_ms = unit_backoff_ms, "--unit-backoff-ms", UNIT_BACKOFF_MS;
            relay.unit_backoff_max_ms = unit_backoff_max_ms, "--unit-backoff-max-ms", UNIT_BACKOFF_MS;
        }
        if let Some(level) = &self.log_level {
            check_log_level(level).map_err(|m| bad("--log-level", m))?;
            c.log.level = level.clone();
        }
        *cfg = c;
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------
// Printing
// ---------------------------------------------------------------------------------------

/// The configuration as TOML, in the section and key order of design.md §4
/// (`mbgate check-config`). `parse(&to_toml(cfg), ..)` gives back `cfg`.
pub fn to_toml(cfg: &Config) -> String {
    toml::to_string(cfg).expect("Config has only TOML-representable fields")
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    const F: &str = "config/test.toml";

    fn err(text: &str) -> String {
        parse(text, F).expect_err("should be rejected").to_string()
    }

    /// The message names the file, the line and the key.
    #[track_caller]
    fn assert_err(text: &str, line: usize, key: &str, contains: &str) {
        let e = err(text);
        let at = format!("{F}:{line}:");
        assert!(e.starts_with(&at), "{e:?} should start with {at:?}");
        assert!(e.contains(&format!(": {key}: ")), "{e:?} should name {key}");
        assert!(e.contains(contains), "{e:?} should contain {contains:?}");
    }

    #[test]
    fn defaults_are_design_md() {
        let c = Config::default();
        assert_eq!(c.serial.path, "/dev/ttyUSB0");
        assert_eq!(c.serial.baud_rate, 19200);
        assert_eq!(c.serial.data_bits, 8);
        assert_eq!(c.serial.parity, Parity::None);
        assert_eq!(c.serial.stop_bits, 1);
        assert_eq!(c.serial.flow_control, FlowControl::Hardware);
        assert_eq!(c.serial.framing, Framing::Mbap);
        assert_eq!(c.tcp.listen, "0.0.0.0:502".parse().unwrap());
        assert_eq!(c.tcp.max_connections, 32);
        assert_eq!(c.tcp.idle_timeout_ms, 60_000);
        assert_eq!(c.relay.response_timeout_ms, 1000);
        assert_eq!(c.relay.frame_gap_ms, 50);
        assert_eq!(c.relay.max_in_flight, 1);
        assert_eq!(c.relay.max_pending_per_connection, 16);
        assert_eq!(c.relay.queue_depth, 64);
        assert_eq!(c.relay.retries, 0);
        assert!(!c.relay.retry_writes);
        assert_eq!(c.relay.notifications, Notifications::Drop);
        assert_eq!(c.serial.silence_floor_ms, 20);
        assert!(!c.serial.rs485 && !c.serial.echo);
        assert_eq!(c.relay.broadcast_delay_ms, 100);
        assert_eq!(c.relay.broadcast_reply, BroadcastReply::None);
        assert!(c.relay.unit_backoff);
        assert_eq!(c.relay.unit_backoff_after, 3);
        assert_eq!(
            (c.relay.unit_backoff_ms, c.relay.unit_backoff_max_ms),
            (1000, 30_000)
        );
        assert_eq!(c.log.level, "info");
        assert!(!c.log.traffic);
    }

    #[test]
    fn empty_file_is_defaults() {
        assert_eq!(parse("", F).unwrap(), Config::default());
        assert_eq!(parse("\n# nothing\n\n", F).unwrap(), Config::default());
        assert_eq!(
            parse("[serial]\n[tcp]\n[relay]\n[log]\n", F).unwrap(),
            Config::default()
        );
    }

    #[test]
    fn shipped_file_is_defaults() {
        let text = include_str!("../config/mbgate.toml");
        assert_eq!(
            parse(text, "config/mbgate.toml").unwrap(),
            Config::default()
        );
        // Every key is spelled out in the shipped file.
        let printed = to_toml(&Config::default());
        for line in printed.lines().filter(|l| l.contains(" = ")) {
            let key = line.split(" = ").next().unwrap();
            assert!(
                text.lines().any(|l| l.starts_with(&format!("{key} = "))),
                "{key} missing from config/mbgate.toml"
            );
        }
    }

    #[test]
    fn partial_section_keeps_other_defaults() {
        let c = parse(
            "[serial]\nbaud_rate = 9600\nparity = \"even\"\n[relay]\nnotifications = \"broadcast\"\n",
            F,
        )
        .unwrap();
        let mut want = Config::default();
        want.serial.baud_rate = 9600;
        want.serial.parity = Parity::Even;
        want.relay.notifications = Notifications::Broadcast;
        assert_eq!(c, want);
    }

    #[test]
    fn dotted_keys_and_inline_tables_work() {
        let c = parse(
            "serial.baud_rate = 9600\ntcp = { max_connections = 4 }\n",
            F,
        )
        .unwrap();
        assert_eq!(c.serial.baud_rate, 9600);
        assert_eq!(c.tcp.max_connections, 4);
    }

    #[test]
    fn syntax_error_names_file_line_column() {
        let e = err("[serial]\nbaud_rate = 19200\npath = \"/dev/ttyS0\n");
        assert!(e.starts_with(&format!("{F}:3:")), "{e}");
        assert!(e.contains("serial.path: TOML syntax error"), "{e}");

        let e = err("[serial]\n\n\nbaud_rate = = 5\n");
        assert!(
            e.starts_with(&format!("{F}:4:13: serial.baud_rate: ")),
            "{e}"
        );

        let e = err("[serial\n");
        assert!(e.starts_with(&format!("{F}:1:")), "{e}");
        assert!(e.contains("TOML syntax error"), "{e}");
    }

    #[test]
    fn duplicate_key_is_an_error() {
        let e = err("[tcp]\nmax_connections = 3\nmax_connections = 4\n");
        assert!(e.starts_with(&format!("{F}:3:")), "{e}");
        assert!(e.contains("tcp.max_connections"), "{e}");
    }

    #[test]
    fn unknown_key_in_each_section() {
        assert_err(
            "[serial]\nbaudrate = 9600\n",
            2,
            "serial.baudrate",
            "unknown key; expected one of path, baud_rate, data_bits, parity, stop_bits, \
             flow_control, framing, silence_floor_ms, rs485, rs485_delay_before_send_ms, \
             rs485_delay_after_send_ms, echo (did you mean `baud_rate`?)",
        );
        assert_err(
            "[tcp]\nlisten = \"0.0.0.0:502\"\n\nmax_conections = 3\n",
            4,
            "tcp.max_conections",
            "unknown key; expected one of listen, max_connections, idle_timeout_ms",
        );
        assert_err(
            "[relay]\ntimeout_ms = 3\n",
            2,
            "relay.timeout_ms",
            "unknown key; expected one of response_timeout_ms,",
        );
        assert_err(
            "[log]\nlevel = \"info\"\ncolour = true\n",
            3,
            "log.colour",
            "unknown key; expected one of level, traffic",
        );
        assert_err(
            "[serial]\n[modbus]\nunit = 1\n",
            2,
            "modbus",
            "unknown key; expected one of serial, tcp, relay, log",
        );
        assert_err(
            "[serial]\n[tcp]\n[relay]\n[log]\n[logs]\n",
            5,
            "logs",
            "(did you mean `log`?)",
        );
    }

    #[test]
    fn unknown_key_column_points_at_key() {
        let e = err("[serial]\n  baudrate = 9600\n");
        assert!(e.starts_with(&format!("{F}:2:3: serial.baudrate: ")), "{e}");
    }

    #[test]
    fn wrong_types() {
        assert_err(
            "[serial]\nbaud_rate = \"fast\"\n",
            2,
            "serial.baud_rate",
            "invalid type: string \"fast\", expected an integer",
        );
        assert_err(
            "[serial]\npath = 5\n",
            2,
            "serial.path",
            "expected a string",
        );
        assert_err(
            "[relay]\nretry_writes = \"yes\"\n",
            2,
            "relay.retry_writes",
            "invalid type",
        );
        assert_err("[tcp]\nlisten = 502\n", 2, "tcp.listen", "0.0.0.0:502");
        assert_err("[log]\ntraffic = 1\n", 2, "log.traffic", "invalid type");
        assert_err(
            "[relay]\nframe_gap_ms = 1.5\n",
            2,
            "relay.frame_gap_ms",
            "integer",
        );
        assert_err(
            "serial = 5\n",
            1,
            "serial",
            "invalid type: integer `5`, expected a table ([section])",
        );
        assert_err(
            "[serial]\nparity = 1\n",
            2,
            "serial.parity",
            "expected a string, one of none, even, odd",
        );
        assert_err(
            "[relay]\nqueue_depth = 99999999999999999999\n",
            2,
            "relay.queue_depth",
            "must be between 1 and 65536",
        );
    }

    #[test]
    fn bad_enum_values() {
        assert_err(
            "[serial]\nparity = \"mark\"\n",
            2,
            "serial.parity",
            "invalid value \"mark\"; expected one of none, even, odd",
        );
        assert_err(
            "[serial]\nflow_control = \"rts\"\n",
            2,
            "serial.flow_control",
            "expected one of hardware, software, none",
        );
        assert_err(
            "[serial]\nframing = \"tcp\"\n",
            2,
            "serial.framing",
            "invalid value \"tcp\"; expected one of mbap, rtu, ascii",
        );
        assert_err(
            "[relay]\nnotifications = \"all\"\n",
            2,
            "relay.notifications",
            "expected one of drop, broadcast",
        );
        assert_err(
            "[serial]\nparity = \"Even\"\n",
            2,
            "serial.parity",
            "invalid value",
        );
    }

    #[test]
    fn range_violations() {
        let cases: &[(&str, &str, &str, &str)] = &[
            (
                "serial",
                "baud_rate",
                "49",
                "must be between 50 and 4000000, got 49",
            ),
            (
                "serial",
                "baud_rate",
                "4000001",
                "must be between 50 and 4000000",
            ),
            (
                "serial",
                "baud_rate",
                "-1",
                "must be between 50 and 4000000, got -1",
            ),
            ("serial", "data_bits", "6", "must be 7 or 8, got 6"),
            ("serial", "data_bits", "300", "must be 7 or 8, got 300"),
            ("serial", "stop_bits", "0", "must be 1 or 2"),
            ("serial", "stop_bits", "3", "must be 1 or 2"),
            ("serial", "path", "\"\"", "must not be empty"),
            ("serial", "path", "\"  \"", "must not be empty"),
            (
                "tcp",
                "listen",
                "\"0.0.0.0\"",
                "expected an address like 0.0.0.0:502",
            ),
            (
                "tcp",
                "listen",
                "\"localhost:502\"",
                "expected an address like",
            ),
            ("tcp", "max_connections", "0", "must be between 1 and 4096"),
            (
                "tcp",
                "max_connections",
                "4097",
                "must be between 1 and 4096",
            ),
            ("tcp", "idle_timeout_ms", "-5", "must be 0 (never)"),
            (
                "relay",
                "response_timeout_ms",
                "0",
                "must be between 1 and 600000",
            ),
            (
                "relay",
                "response_timeout_ms",
                "600001",
                "must be between 1 and 600000",
            ),
            ("relay", "frame_gap_ms", "0", "must be between 1 and 60000"),
            (
                "relay",
                "frame_gap_ms",
                "60001",
                "must be between 1 and 60000",
            ),
            ("relay", "max_in_flight", "0", "must be between 1 and 255"),
            ("relay", "max_in_flight", "256", "must be between 1 and 255"),
            (
                "relay",
                "max_pending_per_connection",
                "0",
                "must be between 1 and 1024",
            ),
            (
                "relay",
                "max_pending_per_connection",
                "1025",
                "must be between 1 and 1024",
            ),
            ("relay", "queue_depth", "0", "must be between 1 and 65536"),
            (
                "relay",
                "queue_depth",
                "65537",
                "must be between 1 and 65536",
            ),
            ("relay", "retries", "11", "must be between 0 and 10"),
            ("relay", "retries", "-1", "must be between 0 and 10"),
            (
                "serial",
                "silence_floor_ms",
                "1001",
                "must be between 0 and 1000",
            ),
            (
                "serial",
                "rs485_delay_before_send_ms",
                "-1",
                "must be between 0 and 1000",
            ),
            (
                "relay",
                "broadcast_delay_ms",
                "60001",
                "must be between 0 and 60000",
            ),
            (
                "relay",
                "unit_backoff_after",
                "0",
                "must be between 1 and 100",
            ),
            (
                "relay",
                "unit_backoff_max_ms",
                "0",
                "must be between 1 and 3600000",
            ),
            (
                "log",
                "level",
                "\"verbose\"",
                "must be one of trace, debug, info, warn, error",
            ),
            ("log", "level", "\"INFO\"", "must be one of"),
        ];
        for (section, key, value, msg) in cases {
            // Put the bad key on line 3, column 13 (after a comment line).
            let pad = " ".repeat(12 - key.len().min(12));
            let text = format!("[{section}]\n# comment\n{pad}{key} = {value}\n");
            let col = pad.len() + key.len() + 4;
            let e = err(&text);
            let want = format!("{F}:3:{col}: {section}.{key}: {msg}");
            assert!(e.starts_with(&want), "{e:?} should start with {want:?}");
        }
    }

    #[test]
    fn range_edges_are_accepted() {
        let text = "[serial]\nbaud_rate = 50\ndata_bits = 7\nstop_bits = 2\n\
                    [tcp]\nlisten = \"[::1]:1502\"\nmax_connections = 4096\nidle_timeout_ms = 0\n\
                    [relay]\nresponse_timeout_ms = 600000\nframe_gap_ms = 1\nmax_in_flight = 255\n\
                    max_pending_per_connection = 1024\nqueue_depth = 65536\nretries = 10\n\
                    [log]\nlevel = \"trace\"\n";
        let c = parse(text, F).unwrap();
        assert_eq!(c.serial.baud_rate, 50);
        assert_eq!(c.tcp.listen, "[::1]:1502".parse().unwrap());
        assert_eq!(c.relay.queue_depth, 65536);
        assert_eq!(c.relay.retries, 10);
        assert_eq!(
            parse("[serial]\nbaud_rate = 4000000\n", F)
                .unwrap()
                .serial
                .baud_rate,
            4_000_000
        );
    }

    #[test]
    fn load_names_file_and_os_error() {
        let e = load(Path::new("/nonexistent/mbgate.toml")).unwrap_err();
        let msg = e.to_string();
        assert!(msg.starts_with("/nonexistent/mbgate.toml: "), "{msg}");
        assert!(msg.contains("No such file or directory"), "{msg}");
        assert!(matches!(e, ConfigError::Read { .. }));
    }

    #[test]
    fn load_reads_file_and_reports_its_name() {
        let dir = std::env::temp_dir().join(format!("mbgate-config-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let good = dir.join("good.toml");
        std::fs::write(&good, "[serial]\npath = \"/dev/ttyAMA0\"\n").unwrap();
        assert_eq!(load(&good).unwrap().serial.path, "/dev/ttyAMA0");
        let bad = dir.join("bad.toml");
        std::fs::write(&bad, "[serial]\n\n\n\n\n\nbaud_rate = 10\n").unwrap();
        let msg = load(&bad).unwrap_err().to_string();
        assert_eq!(
            msg,
            format!(
                "{}:7:13: serial.baud_rate: must be between 50 and 4000000, got 10",
                bad.display()
            )
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    fn non_default() -> Config {
        Config {
            serial: SerialConfig {
                path: "/dev/serial/by-id/usb-FTDI \"quoted\" \\ name".into(),
                baud_rate: 115_200,
                data_bits: 7,
                parity: Parity::Odd,
                stop_bits: 2,
                flow_control: FlowControl::Software,
                framing: Framing::Rtu,
                silence_floor_ms: 0,
                rs485: true,
                rs485_delay_before_send_ms: 2,
                rs485_delay_after_send_ms: 1000,
                echo: true,
            },
            tcp: TcpConfig {
                listen: "[::]:1502".parse().unwrap(),
                max_connections: 4096,
                idle_timeout_ms: 0,
            },
            relay: RelayConfig {
                response_timeout_ms: 600_000,
                frame_gap_ms: 1,
                max_in_flight: 255,
                max_pending_per_connection: 1,
                queue_depth: 65_536,
                retries: 10,
                retry_writes: true,
                notifications: Notifications::Broadcast,
                broadcast_delay_ms: 0,
                broadcast_reply: BroadcastReply::Echo,
                unit_backoff: false,
                unit_backoff_after: 100,
                unit_backoff_ms: 1,
                unit_backoff_max_ms: 3_600_000,
            },
            log: LogConfig {
                level: "trace".into(),
                traffic: true,
            },
        }
    }

    #[test]
    fn round_trip() {
        for cfg in [Config::default(), non_default()] {
            let text = to_toml(&cfg);
            assert_eq!(parse(&text, "printed").unwrap(), cfg, "{text}");
        }
    }

    #[test]
    fn printed_layout_follows_design_md() {
        let text = to_toml(&Config::default());
        let headers: Vec<&str> = text.lines().filter(|l| l.starts_with('[')).collect();
        assert_eq!(headers, ["[serial]", "[tcp]", "[relay]", "[log]"]);
        assert!(text.contains("[serial]\npath = \"/dev/ttyUSB0\"\nbaud_rate = 19200\n"));
        assert!(text.contains("listen = \"0.0.0.0:502\"\n"));
        assert!(text.contains("parity = \"none\"\n"));
    }

    #[test]
    fn overrides_apply_every_field() {
        let want = non_default();
        let o = Overrides {
            serial: Some(want.serial.path.clone()),
            listen: Some(want.tcp.listen),
            baud: Some(want.serial.baud_rate),
            data_bits: Some(want.serial.data_bits),
            parity: Some(want.serial.parity),
            stop_bits: Some(want.serial.stop_bits),
            flow_control: Some(want.serial.flow_control),
            framing: Some(want.serial.framing),
            silence_floor_ms: Some(want.serial.silence_floor_ms),
            rs485: Some(want.serial.rs485),
            rs485_delay_before_send_ms: Some(want.serial.rs485_delay_before_send_ms),
            rs485_delay_after_send_ms: Some(want.serial.rs485_delay_after_send_ms),
            echo: Some(want.serial.echo),
            response_timeout_ms: Some(want.relay.response_timeout_ms),
            frame_gap_ms: Some(want.relay.frame_gap_ms),
            max_in_flight: Some(want.relay.max_in_flight),
            max_pending_per_connection: Some(want.relay.max_pending_per_connection),
            queue_depth: Some(want.relay.queue_depth),
            max_connections: Some(want.tcp.max_connections),
            idle_timeout_ms: Some(want.tcp.idle_timeout_ms),
            retries: Some(want.relay.retries),
            retry_writes: Some(want.relay.retry_writes),
            notifications: Some(want.relay.notifications),
            broadcast_delay_ms: Some(want.relay.broadcast_delay_ms),
            broadcast_reply: Some(want.relay.broadcast_reply),
            unit_backoff: Some(want.relay.unit_backoff),
            unit_backoff_after: Some(want.relay.unit_backoff_after),
            unit_backoff_ms: Some(want.relay.unit_backoff_ms),
            unit_backoff_max_ms: Some(want.relay.unit_backoff_max_ms),
            log_level: Some(want.log.level.clone()),
            traffic: Some(want.log.traffic),
        };
        let mut cfg = Config::default();
        o.apply(&mut cfg).unwrap();
        assert_eq!(cfg, want);

        // No flags: nothing changes.
        let mut cfg = want.clone();
        Overrides::default().apply(&mut cfg).unwrap();
        assert_eq!(cfg, want);
    }

    #[test]
    fn overrides_validate_and_name_the_flag() {
        // As typed on the command line. (`--log-level` is refused by clap itself, see
        // below; `apply` checks it too for callers that build `Overrides` in code.)
        let cases: [(&[&str], &str); 11] = [
            (
                &["--baud", "10"],
                "--baud: must be between 50 and 4000000, got 10",
            ),
            (&["--data-bits", "9"], "--data-bits: must be 7 or 8, got 9"),
            (&["--stop-bits", "0"], "--stop-bits: must be 1 or 2, got 0"),
            (&["--serial", ""], "--serial: must not be empty"),
            (
                &["--response-timeout-ms", "0"],
                "--response-timeout-ms: must be between 1 and 600000, got 0",
            ),
            (
                &["--frame-gap-ms", "60001"],
                "--frame-gap-ms: must be between 1 and 60000",
            ),
            (
                &["--max-in-flight", "256"],
                "--max-in-flight: must be between 1 and 255",
            ),
            (
                &["--max-pending-per-connection", "0"],
                "--max-pending-per-connection: must be between 1 and 1024",
            ),
            (
                &["--queue-depth", "70000"],
                "--queue-depth: must be between 1 and 65536",
            ),
            (
                &["--max-connections", "0"],
                "--max-connections: must be between 1 and 4096",
            ),
            (&["--retries", "11"], "--retries: must be between 0 and 10"),
        ];
        for (args, want) in cases {
            let mut cfg = Config::default();
            let e = cli(args).unwrap().apply(&mut cfg).unwrap_err().to_string();
            assert!(e.starts_with(want), "{e:?} should start with {want:?}");
            assert_eq!(cfg, Config::default(), "a failed apply must not change cfg");
        }
        let level = Overrides {
            log_level: Some("loud".into()),
            ..Default::default()
        };
        let e = level.apply(&mut Config::default()).unwrap_err().to_string();
        assert!(e.starts_with("--log-level: must be one of trace, debug, info, warn, error"));
        // A later bad flag leaves earlier good ones unapplied too.
        let mut cfg = Config::default();
        let o = Overrides {
            baud: Some(9600),
            retries: Some(99),
            ..Default::default()
        };
        assert!(o.apply(&mut cfg).is_err());
        assert_eq!(cfg, Config::default());
    }

    #[derive(Parser, Debug)]
    struct Cli {
        #[command(flatten)]
        overrides: Overrides,
    }

    fn cli(args: &[&str]) -> Result<Overrides, clap::Error> {
        Cli::try_parse_from(std::iter::once("mbgate").chain(args.iter().copied()))
            .map(|c| c.overrides)
    }

    #[test]
    fn command_line_flags_parse() {
        let o = cli(&[
            "--serial",
            "/dev/ttyS1",
            "--listen",
            "127.0.0.1:1502",
            "--baud",
            "9600",
            "--data-bits",
            "7",
            "--parity",
            "even",
            "--stop-bits",
            "2",
            "--flow-control",
            "none",
            "--framing",
            "rtu",
            "--rs485",
            "--echo=false",
            "--broadcast-reply",
            "echo",
            "--unit-backoff-after",
            "5",
            "--response-timeout-ms",
            "500",
            "--frame-gap-ms",
            "20",
            "--max-in-flight",
            "2",
            "--max-pending-per-connection",
            "4",
            "--queue-depth",
            "8",
            "--max-connections",
            "3",
            "--idle-timeout-ms",
            "0",
            "--retries",
            "1",
            "--retry-writes",
            "--notifications",
            "broadcast",
            "--log-level",
            "debug",
            "--traffic",
        ])
        .unwrap();
        assert_eq!(o.serial.as_deref(), Some("/dev/ttyS1"));
        assert_eq!(o.listen, Some("127.0.0.1:1502".parse().unwrap()));
        assert_eq!(o.parity, Some(Parity::Even));
        assert_eq!(o.flow_control, Some(FlowControl::None));
        assert_eq!(o.framing, Some(Framing::Rtu));
        assert_eq!((o.rs485, o.echo), (Some(true), Some(false)));
        assert_eq!(o.broadcast_reply, Some(BroadcastReply::Echo));
        assert_eq!(o.unit_backoff_after, Some(5));
        assert_eq!(o.notifications, Some(Notifications::Broadcast));
        assert_eq!(o.retry_writes, Some(true));
        assert_eq!(o.traffic, Some(true));
        assert_eq!(o.log_level.as_deref(), Some("debug"));
        let mut cfg = Config::default();
        o.apply(&mut cfg).unwrap();
        assert_eq!(cfg.serial.baud_rate, 9600);
        assert_eq!(cfg.relay.max_pending_per_connection, 4);
        assert_eq!(cfg.tcp.idle_timeout_ms, 0);

        assert_eq!(cli(&[]).unwrap(), Overrides::default());
        let o = cli(&["--traffic=false", "--retry-writes=false"]).unwrap();
        assert_eq!((o.traffic, o.retry_writes), (Some(false), Some(false)));
    }

    #[test]
    fn command_line_rejects_bad_values_naming_the_flag() {
        for (args, flag) in [
            (&["--parity", "mark"][..], "--parity"),
            (&["--listen", "0.0.0.0"][..], "--listen"),
            (&["--baud", "fast"][..], "--baud"),
            (&["--log-level", "loud"][..], "--log-level"),
            (&["--traffic=maybe"][..], "--traffic"),
        ] {
            let e = cli(args).unwrap_err();
            let msg = e.to_string();
            assert!(msg.contains(flag), "{msg}");
            assert_eq!(e.exit_code(), 2);
        }
        let msg = cli(&["--listen", "0.0.0.0"]).unwrap_err().to_string();
        assert!(
            msg.contains("expected an address like 0.0.0.0:502"),
            "{msg}"
        );
    }
}
