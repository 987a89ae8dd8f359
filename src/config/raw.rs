//! What every reader of a table in the file shares, here so that none of them imports
//! another: a value as the checks see it ([`Raw`], from a TOML value by [`raw_value`]),
//! a table's entries in the order of the file ([`entries`]), a value the file got wrong
//! ([`Bad`]) and the expected name closest to a misspelt one ([`suggest`]).

use std::borrow::Cow;
use toml::de::{DeTable, DeValue};
use toml::Spanned;

/// A value as found in the file or given as a flag, before it is checked.
#[derive(Debug, Clone, PartialEq)]
pub enum Raw {
    /// A TOML integer, or a flag's value that parses as one.
    Int(i128),
    /// A TOML boolean, or a flag's `true`/`false`.
    Bool(bool),
    /// A TOML string, or a flag's value taken as text.
    Str(String),
    /// Any other TOML value, as described in messages (`floating point `1.5``).
    Other(String),
}

impl Raw {
    pub(super) fn invalid(&self, expected: &str) -> String {
        let found = match self {
            Raw::Int(v) => format!("integer `{v}`"),
            Raw::Bool(b) => format!("boolean `{b}`"),
            Raw::Str(s) => format!("string {s:?}"),
            Raw::Other(what) => what.clone(),
        };
        format!("invalid type: {found}, expected {expected}")
    }
}

/// A TOML value as the checks see it.
pub(super) fn raw_value(v: &DeValue) -> Raw {
    match v {
        DeValue::Integer(i) => {
            // Beyond i128 (far beyond any range): saturated, which keeps the sign.
            let negative = i.as_str().starts_with('-');
            let beyond = if negative { i128::MIN } else { i128::MAX };
            Raw::Int(i128::from_str_radix(i.as_str(), i.radix()).unwrap_or(beyond))
        }
        DeValue::Boolean(b) => Raw::Bool(*b),
        DeValue::String(s) => Raw::Str(s.to_string()),
        DeValue::Float(f) => Raw::Other(format!("floating point `{}`", f.as_str())),
        DeValue::Datetime(d) => Raw::Other(format!("datetime `{d}`")),
        DeValue::Array(_) => Raw::Other("array".into()),
        DeValue::Table(_) => Raw::Other("table".into()),
    }
}

/// One key of a table and its value, both with their place in the file.
pub(super) type Entry<'a, 'i> = (&'a Spanned<Cow<'i, str>>, &'a Spanned<DeValue<'i>>);

/// A table's entries in the order of the file (`DeTable` keeps them sorted by name).
pub(super) fn entries<'a, 'i>(table: &'a DeTable<'i>) -> Vec<Entry<'a, 'i>> {
    let mut all: Vec<_> = table.iter().collect();
    all.sort_by_key(|(k, _)| k.span().start);
    all
}

/// A value the file got wrong: where, which key, why. The file reader turns it into a
/// [`super::ConfigError`] naming file, line and column.
#[derive(Debug)]
pub(super) struct Bad {
    pub(super) at: usize,
    pub(super) key: String,
    pub(super) message: String,
}

/// A [`Bad`] at byte `at`, for `key`.
pub(super) fn bad<T>(at: usize, key: &str, message: impl Into<String>) -> Result<T, Bad> {
    Err(Bad {
        at,
        key: key.to_owned(),
        message: message.into(),
    })
}

/// The expected name closest to a misspelt `name`, if one is close enough.
pub(super) fn suggest<'a>(name: &str, expected: &[&'a str]) -> Option<&'a str> {
    let norm = |s: &str| -> String {
        s.chars()
            .filter(|c| *c != '_' && *c != '-')
            .flat_map(char::to_lowercase)
            .collect()
    };
    let n = norm(name);
    expected
        .iter()
        .map(|e| (strsim::levenshtein(&n, &norm(e)), *e))
        .filter(|(d, e)| *d <= 2.max(e.len() / 4))
        .min_by_key(|(d, _)| *d)
        .map(|(_, e)| e)
}
