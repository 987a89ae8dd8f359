//! What every reader of a table in the file shares, here so that none of them imports
//! another: a value as the checks see it ([`Raw`], from a TOML value by [`raw_value`]),
//! a table's entries in the order of the file ([`entries`]), a value the file got wrong
//! ([`Bad`]), the place inside a value that a [`ValueError`] names ([`place`]) and the
//! expected name closest to a misspelt one ([`suggest`]).

use super::error::{Step, ValueError};
use super::Key;
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
    /// A TOML array (never a flag's value).
    List(Vec<Raw>),
    /// A TOML table, its keys in the order of the file (never a flag's value).
    Table(Vec<(String, Raw)>),
    /// Any other TOML value, as described in messages (`floating point `1.5``).
    Other(String),
}

impl Raw {
    pub(super) fn invalid(&self, expected: &str) -> ValueError {
        let found = match self {
            Raw::Int(v) => format!("integer `{v}`"),
            Raw::Bool(b) => format!("boolean `{b}`"),
            Raw::Str(s) => format!("string {s:?}"),
            Raw::List(_) => "array".into(),
            Raw::Table(_) => "table".into(),
            Raw::Other(what) => what.clone(),
        };
        ValueError::new(format!("invalid type: {found}, expected {expected}"))
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
        DeValue::Array(items) => Raw::List(items.iter().map(|i| raw_value(i.get_ref())).collect()),
        DeValue::Table(t) => Raw::Table(
            entries(t)
                .into_iter()
                .map(|(k, v)| (k.get_ref().to_string(), raw_value(v.get_ref())))
                .collect(),
        ),
    }
}

/// Where in the file the part of `v` that `e` names is, and its full key: `key` is
/// `v`'s (`listen[0]`), an item of an array of tables adds `[i]` (`listen[0].write[1]`),
/// an item of an array of values keeps the array's key at the item's place, and a key
/// the table lacks is named at the table.
pub(super) fn place(v: &Spanned<DeValue>, key: &str, e: &ValueError) -> Bad {
    let (mut at, mut key, mut cur) = (v.span().start, key.to_owned(), v);
    for step in &e.path {
        match (step, cur.get_ref()) {
            (Step::Item(i), DeValue::Array(items)) if *i < items.len() => {
                cur = &items[*i];
                if let DeValue::Table(_) = cur.get_ref() {
                    key += &format!("[{i}]");
                }
                at = cur.span().start;
            }
            (Step::Value(k), DeValue::Table(t)) => {
                key += &format!(".{k}");
                match t.get_key_value(k.as_str()) {
                    Some((_, value)) => {
                        cur = value;
                        at = cur.span().start;
                    }
                    None => break,
                }
            }
            (Step::Key(k), DeValue::Table(t)) => {
                key += &format!(".{k}");
                if let Some((name, _)) = t.get_key_value(k.as_str()) {
                    at = name.span().start;
                }
                break;
            }
            _ => break,
        }
    }
    Bad {
        at,
        key,
        message: e.message.clone(),
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

/// A table of the file (`raw`, a [`Raw::Table`]) read by its declared `keys`: each
/// value checked by its declaration, an unknown key refused naming the expected ones
/// (`not_table`: the message for a value that is no table). Also the keys it gave, in
/// the order of the file.
pub(super) fn read_table<C: Default>(
    raw: &Raw,
    keys: &[Key<C>],
    not_table: &str,
) -> Result<(C, Vec<&'static str>), ValueError> {
    let Raw::Table(entries) = raw else {
        return Err(ValueError::new(not_table));
    };
    let (mut table, mut given) = (C::default(), Vec::new());
    for (name, value) in entries {
        let Some(key) = keys.iter().find(|k| k.name == name) else {
            let names: Vec<&str> = keys.iter().map(|k| k.name).collect();
            let mut m = format!("unknown key; expected one of {}", names.join(", "));
            if let Some(s) = suggest(name, &names) {
                m += &format!(" (did you mean `{s}`?)");
            }
            return Err(ValueError::new(m).key(name));
        };
        (key.set)(&mut table, value).map_err(|e| e.value(name))?;
        given.push(key.name);
    }
    Ok((table, given))
}
