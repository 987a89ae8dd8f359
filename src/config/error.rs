//! Why a configuration was rejected, and where: the file (or the flag), the line and
//! column, and the key, found from the value's place in the text or, for a file that
//! does not parse, from the text around it.

use std::path::PathBuf;

/// Why a configuration was rejected. The `Display` text is the whole message for the
/// operator: it names the file, the line and column, and the key (or the flag).
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read (missing, permissions, not UTF-8...).
    #[error("{}: cannot read the configuration file: {source}", path.display())]
    Read {
        /// The file named (`--config` or the default path).
        path: PathBuf,
        /// What the system said.
        source: std::io::Error,
    },
    /// The text is not valid TOML, or a key is unknown, has the wrong type or a value
    /// out of range. `line`/`column` (1-based) point at the value, or at the key for an
    /// unknown key; `key` is the full dotted key (`serial.baud_rate`) when it can be told.
    #[error("{origin}:{line}:{column}: {}{message}", key_prefix(.key))]
    Invalid {
        /// Where the text came from: the file's path, or a name for a text given in code.
        origin: String,
        /// 1-based line of the value (or of the unknown key).
        line: usize,
        /// 1-based column on that line.
        column: usize,
        /// The full dotted key, when it can be told.
        key: Option<String>,
        /// What is wrong, for the operator.
        message: String,
    },
    /// A command-line override is out of range; `flag` is e.g. `--baud`.
    #[error("{flag}: {message}")]
    Override {
        /// The flag with its dashes, e.g. `--baud`.
        flag: String,
        /// What is wrong with its value.
        message: String,
    },
}

/// Why a value was refused, and where inside it when it is an array or a table: the
/// file's reader turns it into a [`ConfigError::Invalid`] at that place ([`super::raw`]),
/// a flag's into a [`ConfigError::Override`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{message}")]
pub(crate) struct ValueError {
    /// What is wrong, for the operator, without the key.
    pub(crate) message: String,
    /// From the value down to the part that is wrong, outermost first; empty: the
    /// value itself.
    pub(crate) path: Vec<Step>,
}

/// One step down into a value, to the part a [`ValueError`] is about.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Step {
    /// The item of an array at this index.
    Item(usize),
    /// The value of this key of a table (the table itself when the key is missing).
    Value(String),
    /// This key of a table, not its value (an unknown key).
    Key(String),
}

impl ValueError {
    /// The value itself is wrong.
    pub(crate) fn new(message: impl Into<String>) -> Self {
        Self {
            message: message.into(),
            path: Vec::new(),
        }
    }

    /// The error was found in the item `i` of an array.
    pub(crate) fn item(mut self, i: usize) -> Self {
        self.path.insert(0, Step::Item(i));
        self
    }

    /// The error was found in the value of key `k` of a table.
    pub(crate) fn value(mut self, k: &str) -> Self {
        self.path.insert(0, Step::Value(k.to_owned()));
        self
    }

    /// The key `k` of a table is the error itself (unknown).
    pub(crate) fn key(mut self, k: &str) -> Self {
        self.path.insert(0, Step::Key(k.to_owned()));
        self
    }
}

impl From<String> for ValueError {
    fn from(message: String) -> Self {
        Self::new(message)
    }
}

impl From<ValueError> for String {
    fn from(e: ValueError) -> Self {
        e.message
    }
}

impl From<&str> for ValueError {
    fn from(message: &str) -> Self {
        Self::new(message)
    }
}

fn key_prefix(key: &Option<String>) -> String {
    key.as_ref().map(|k| format!("{k}: ")).unwrap_or_default()
}

pub(super) fn syntax_error(text: &str, origin: &str, err: &toml::de::Error) -> ConfigError {
    let (line, column) = err.span().map_or((1, 1), |s| line_col(text, s.start));
    let message = err.message().trim().replace('\n', "; ");
    ConfigError::Invalid {
        origin: origin.to_owned(),
        line,
        column,
        key: key_on_line(text, line),
        message: format!("TOML syntax error: {message}"),
    }
}

/// 1-based line and column (in characters) of byte `offset` in `text`.
pub(super) fn line_col(text: &str, offset: usize) -> (usize, usize) {
    let mut offset = offset.min(text.len());
    while !text.is_char_boundary(offset) {
        offset -= 1;
    }
    let before = &text[..offset];
    let line = before.matches('\n').count() + 1;
    let line_start = before.rfind('\n').map_or(0, |i| i + 1);
    (line, before[line_start..].chars().count() + 1)
}

/// Best-effort name of the key on a line of a file that failed to parse (there is no
/// table to ask): `section.key` for `key = ...`, `section` for `[section]`.
fn key_on_line(text: &str, line: usize) -> Option<String> {
    fn bare(s: &str) -> bool {
        !s.is_empty()
            && s.chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.'))
    }
    fn header(l: &str) -> Option<&str> {
        let inner = l.trim().strip_prefix('[')?;
        let name = inner[..inner.find(']')?].trim();
        (!inner.starts_with('[') && bare(name)).then_some(name)
    }
    let lines: Vec<&str> = text.split('\n').collect();
    let current = lines.get(line.checked_sub(1)?)?;
    if current.trim_start().starts_with('[') {
        return header(current).map(str::to_owned);
    }
    let section = lines[..line - 1].iter().rev().find_map(|l| header(l));
    let key = current[..current.find('=')?].trim();
    bare(key).then(|| match section {
        Some(s) => format!("{s}.{key}"),
        None => key.to_owned(),
    })
}
