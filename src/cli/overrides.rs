//! The command-line flags that override the configuration (docs/design.md §3), built
//! from the declarations in [`crate::config::KEYS`]: one flag a key for `mbgate run` and
//! `check-config` ([`Overrides`]), the serial port's for `mbgate sim` and the client
//! (`PortFlags`). A flag's value passes the same checks as the file's; its help
//! shows the key's range, name and default.

use crate::config::{
    parse_listen, parse_optional_address, Check, Config, ConfigError, Key, Raw, SerialConfig,
    Setting, ValueKind, KEYS, METRICS_EXAMPLE,
};
use clap::builder::{PossibleValue, PossibleValuesParser, TypedValueParser};
use clap::{Arg, ArgGroup, ArgMatches, Args, Command, FromArgMatches};

/// Every key's flag (`mbgate run --baud 9600 ...`). Flatten into a subcommand with
/// `#[command(flatten)]`, then [`Flags::apply`] on the loaded (or default) configuration.
pub type Overrides = Flags<false>;

/// The serial port's flags (`--baud`, `--data-bits`, `--parity`, `--stop-bits`,
/// `--flow-control`), for `mbgate sim` and the client. In the group [`PORT_GROUP`].
pub(crate) type PortFlags = Flags<true>;

/// The clap group of the [`PortFlags`], e.g. to make them require another argument.
pub(crate) const PORT_GROUP: &str = "serial-port";

/// The flags given, in the order of [`KEYS`]; `PORT` keeps only the port's.
#[derive(Debug, Clone, Default)]
pub struct Flags<const PORT: bool> {
    given: Vec<(&'static Key, Raw)>,
}

/// The same flags with the same values.
impl<const PORT: bool> PartialEq for Flags<PORT> {
    fn eq(&self, other: &Self) -> bool {
        let flags = |f: &Self| {
            f.given
                .iter()
                .map(|(k, v)| (k.flag, v.clone()))
                .collect::<Vec<_>>()
        };
        flags(self) == flags(other)
    }
}

impl<const PORT: bool> Flags<PORT> {
    fn keys() -> impl Iterator<Item = &'static Key> {
        KEYS.iter().filter(|k| k.port || !PORT)
    }

    /// Gives `--flag` (without its dashes) `value`, as if typed: for callers that
    /// build flags in code. False when there is no such flag.
    pub fn set(&mut self, flag: &str, value: Raw) -> bool {
        let Some(key) = Self::keys().find(|k| k.flag == flag) else {
            return false;
        };
        self.given.retain(|(k, _)| k.flag != flag);
        self.given.push((key, value));
        true
    }

    /// Whether `--flag` was given.
    pub fn given(&self, flag: &str) -> bool {
        self.given.iter().any(|(k, _)| k.flag == flag)
    }

    /// Applies every flag given to `cfg`, checking what the file's values are checked
    /// for. On error `cfg` is left unchanged and the message names the flag.
    pub fn apply(&self, cfg: &mut Config) -> Result<(), ConfigError> {
        let bad = |flag: &str, message| ConfigError::Override {
            flag: format!("--{flag}"),
            message,
        };
        let mut c = cfg.clone();
        for (key, value) in &self.given {
            // With several lines (or listeners) a flag could mean any of them.
            let tables = match key.section {
                "serial" | "relay" if !cfg.single_line() => Some("[[line]]"),
                "tcp" if !cfg.single_listener() => Some("[[listen]]"),
                _ => None,
            };
            if let Some(tables) = tables {
                let m = format!("the file describes the gateway as {tables} tables: set it there");
                return Err(bad(key.flag, m));
            }
            // A file that only dials its masters opens no listener: --listen opens
            // one, and the listener's other flags mean nothing without it.
            if key.section == "tcp" && c.dial_only {
                if key.name != "listen" && !self.given("listen") {
                    let m = "the file only dials its masters and opens no listener: give --listen ADDR too, or write [tcp] or [[listen]]".to_owned();
                    return Err(bad(key.flag, m));
                }
                c.dial_only = false;
            }
            (key.set)(&mut c, value).map_err(|e| bad(key.flag, e.into()))?;
        }
        // Flags that contradict each other, or the file: name the flag that was given
        // (the first key's when both were).
        if let Some(conflict) = c.conflict() {
            let (first, other) = (conflict.key.flag, conflict.other.flag);
            let named = if self.given(other) && !self.given(first) {
                other
            } else {
                first
            };
            let message = format!(
                "{}.{} {}",
                conflict.key.section,
                conflict.key.name,
                conflict.message("")
            );
            return Err(bad(named, message));
        }
        *cfg = c;
        Ok(())
    }

    /// [`Flags::apply`] to serial port settings alone.
    pub(crate) fn apply_serial(&self, serial: &mut SerialConfig) -> Result<(), ConfigError> {
        let mut cfg = Config::default();
        cfg.lines[0].serial = serial.clone();
        self.apply(&mut cfg)?;
        *serial = cfg.lines.swap_remove(0).serial;
        Ok(())
    }
}

/// The flag of `key`: `--baud <N>  Serial speed in bit/s, 50..=4000000
/// [serial.baud_rate] [default: 19200]`.
fn arg(key: &'static Key) -> Arg {
    let mut help = key.help.trim().to_owned();
    let unit = if key.value_name == "MS" { " ms" } else { "" };
    match key.check {
        Check::Range(min, max, None) => help += &format!(", {min}..={max}{unit}"),
        Check::Range(_, _, Some(said)) => help += &format!(", {said}"),
        Check::Any | Check::NonEmpty(_) | Check::OneOf(_) | Check::SocketPath => {}
        Check::Address(_) => {}
    }
    let default = (key.get)(&Config::default());
    let (section, name, default) = (key.section, key.name, default.trim_matches('"'));
    help += &format!(" [{section}.{name}] [default: {default}]");
    let arg = Arg::new(key.flag)
        .long(key.flag)
        .value_name(key.value_name)
        .help(help);
    match (key.kind, key.check) {
        (ValueKind::Int, _) => arg.value_parser(|s: &str| s.parse::<i128>()),
        // `--rs485` alone means true.
        (ValueKind::Bool, _) => arg
            .value_parser(clap::value_parser!(bool))
            .num_args(0..=1)
            .require_equals(true)
            .default_missing_value("true"),
        // `--metrics-listen ""`: none, as in the file.
        (ValueKind::Addr, Check::Address(METRICS_EXAMPLE)) => arg.value_parser(|s: &str| {
            parse_optional_address(s, METRICS_EXAMPLE).map(|_| s.to_owned())
        }),
        (ValueKind::Addr, _) => arg.value_parser(|s: &str| parse_listen(s).map(|_| s.to_owned())),
        (ValueKind::Choice(words), _) => arg.value_parser(words_parser(words)),
        (ValueKind::Str, Check::OneOf(words)) => arg.value_parser(PossibleValuesParser::new(words)),
        (ValueKind::Str, _) => arg,
        (ValueKind::List, _) => unreachable!("no flag takes an array"),
    }
}

impl<const PORT: bool> Args for Flags<PORT> {
    fn augment_args(cmd: Command) -> Command {
        let cmd = cmd.args(Self::keys().map(arg));
        if PORT {
            let ids = Self::keys().map(|k| k.flag);
            cmd.group(ArgGroup::new(PORT_GROUP).multiple(true).args(ids))
        } else {
            cmd
        }
    }

    fn augment_args_for_update(cmd: Command) -> Command {
        Self::augment_args(cmd)
    }
}

impl<const PORT: bool> FromArgMatches for Flags<PORT> {
    fn from_arg_matches(m: &ArgMatches) -> Result<Self, clap::Error> {
        let given = Self::keys().filter_map(|key| {
            let value = match key.kind {
                ValueKind::Int => m.get_one::<i128>(key.flag).map(|v| Raw::Int(*v)),
                ValueKind::Bool => m.get_one::<bool>(key.flag).map(|v| Raw::Bool(*v)),
                _ => m.get_one::<String>(key.flag).map(|v| Raw::Str(v.clone())),
            };
            Some((key, value?))
        });
        Ok(Flags {
            given: given.collect(),
        })
    }

    fn update_from_arg_matches(&mut self, m: &ArgMatches) -> Result<(), clap::Error> {
        *self = Self::from_arg_matches(m)?;
        Ok(())
    }
}

fn words_parser(words: &'static [(&'static str, &'static str)]) -> PossibleValuesParser {
    PossibleValuesParser::new(words.iter().map(|&(word, help)| match help.trim() {
        "" => PossibleValue::new(word),
        help => PossibleValue::new(word).help(help),
    }))
}

/// The value parser of one of the configuration's enums, for a flag of its own
/// (`mbgate sim --framing rtu`): the same words and help as the key's. (A type that is
/// not an enum has no words: nothing is accepted.)
pub(crate) fn choice<T: Setting + Clone + Send + Sync + 'static>(
) -> impl TypedValueParser<Value = T> {
    let words = match T::KIND {
        ValueKind::Choice(words) => words,
        _ => &[],
    };
    words_parser(words).try_map(|word| T::read(&Raw::Str(word), &Check::Any))
}
