//! Reading a configuration file: toml gives the position of every key and value
//! (`DeTable`), each key is checked by its declaration in [`KEYS`], and every error
//! names file, line, column and key: `x.toml:7:13: serial.baud_rate: must be between
//! 50 and 4000000, got 10`. Both forms of docs/design.md §4 and §4.1 are read; a
//! `[[line]]` in `file/line.rs`.

use super::error::{line_col, syntax_error, ConfigError};
use super::raw::{entries, place, raw_value as raw, suggest, Bad, Raw};
use super::{Config, Key, LineConfig, ListenConfig, Step, ValueError, KEYS};
use std::borrow::Cow;
use std::collections::HashMap;
use std::path::Path;
use toml::de::{DeTable, DeValue};
use toml::Spanned;

/// Read and validate the configuration file at `path`. Error messages use `path` as
/// given (relative paths stay relative).
pub fn load(path: &Path) -> Result<Config, ConfigError> {
    let text = read_text(path, MAX_FILE).map_err(|source| ConfigError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    parse(&text, &path.display().to_string())
}

/// The most a configuration file may hold: a hundred times the commented one, and
/// still a small part of a Pi Zero's memory. A path that names something endless
/// (`/dev/zero`, a FIFO a program keeps writing) is refused when it passes this,
/// not read until memory runs out.
pub(crate) const MAX_FILE: u64 = 1 << 20;

/// The text of the file at `path`, refused past `max` bytes (an `InvalidData` error
/// that says so): every file mbgate reads whose size it does not choose goes through
/// here or through a reader bounded as it is.
pub(crate) fn read_text(path: &Path, max: u64) -> std::io::Result<String> {
    use std::io::Read;
    let mut text = String::new();
    std::fs::File::open(path)?
        .take(max + 1)
        .read_to_string(&mut text)?;
    if text.len() as u64 > max {
        let m = format!("larger than {max} bytes, more than such a file ever holds");
        return Err(std::io::Error::new(std::io::ErrorKind::InvalidData, m));
    }
    Ok(text)
}

/// Parse and validate configuration text. `origin` names the text in error messages
/// (normally the file name).
pub fn parse(text: &str, origin: &str) -> Result<Config, ConfigError> {
    let root = DeTable::parse(text).map_err(|e| syntax_error(text, origin, &e))?;
    let lines_form = ["line", "listen"]
        .iter()
        .any(|t| root.get_ref().get(*t).is_some());
    FileReader {
        text,
        origin,
        at: HashMap::new(),
        units: HashMap::new(),
        lines_form,
    }
    .read(root.get_ref())
}

/// The top-level tables; `line` and `listen` are arrays of tables (docs/design.md §4.1).
const TOP: [&str; 11] = [
    "serial", "tcp", "relay", "log", "metrics", "capture", "control", "line", "listen", "role",
    "dial",
];
/// In a `[[listen]]` table, the `[tcp]` key `listen` is called `address`.
pub(super) const LISTEN_RENAMED: &[(&str, &str)] = &[("address", "listen")];

/// What a table calls key `name` of [`KEYS`], given its pairs of (in the file, in
/// [`KEYS`]).
pub(super) fn renamed<'a>(rename: &[(&'a str, &'a str)], name: &'a str) -> &'a str {
    let found = rename.iter().find(|(_, key)| *key == name);
    found.map_or(name, |(file, _)| file)
}

struct FileReader<'t> {
    text: &'t str,
    origin: &'t str,
    /// Where the value of each full key read so far starts.
    at: HashMap<String, usize>,
    /// The `[[line]]` each unit id was given to.
    units: HashMap<u8, String>,
    /// The file describes the gateway as `[[line]]` or `[[listen]]` tables.
    lines_form: bool,
}

/// One `[[line]]` as read from the file: where it starts, the line, whether it lists
/// units.
type LineRead = (usize, LineConfig, bool);

impl FileReader<'_> {
    fn fail<T>(&self, at: usize, key: &str, message: impl Into<String>) -> Result<T, ConfigError> {
        let (line, column) = line_col(self.text, at);
        Err(ConfigError::Invalid {
            origin: self.origin.to_owned(),
            line,
            column,
            key: Some(key.to_owned()),
            message: message.into(),
        })
    }

    fn unknown<T>(
        &self,
        k: &Spanned<Cow<str>>,
        key: &str,
        expected: &[&str],
    ) -> Result<T, ConfigError> {
        let mut m = format!("unknown key; expected one of {}", expected.join(", "));
        if let Some(s) = suggest(k.get_ref(), expected) {
            m += &format!(" (did you mean `{s}`?)");
        } else if let Some(elsewhere) = self.belongs(k.get_ref(), key) {
            m += &format!(" ({elsewhere})");
        }
        self.fail(k.span().start, key, m)
    }

    /// Where `name`, unknown at `key`, belongs when it is (or nearly is) a key of
    /// another table: a top-level `baud_rate` is `[serial]`'s, or in the `[[line]]`
    /// form a line's `serial` table's.
    fn belongs(&self, name: &str, key: &str) -> Option<String> {
        let names: Vec<&str> = KEYS.iter().map(|k| k.name).collect();
        let found = KEYS
            .iter()
            .find(|k| k.name == name)
            .or_else(|| suggest(name, &names).and_then(|n| KEYS.iter().find(|k| k.name == n)))?;
        let (section, name) = (found.section, found.name);
        let in_line = key.starts_with("line[");
        let line_table = matches!(section, "serial" | "relay");
        Some(match (section, in_line || self.lines_form) {
            _ if in_line && line_table => format!(
                "did you mean `{name}` in this line's {section} table: under [line.{section}], \
                 or {section} = {{ {name} = ... }}?"
            ),
            (_, true) if line_table => format!(
                "did you mean `{name}` in a [[line]]'s {section} table, under [line.{section}]?"
            ),
            ("tcp", true) => {
                let name = renamed(LISTEN_RENAMED, name);
                format!("did you mean `{name}` in a [[listen]] table?")
            }
            _ if line_table => format!(
                "did you mean `{name}` under [{section}], or under [line.{section}] in the \
                 [[line]] form?"
            ),
            _ => format!("did you mean `{name}` under [{section}]?"),
        })
    }

    fn read(mut self, root: &DeTable) -> Result<Config, ConfigError> {
        let mut cfg = Config::default();
        let (mut lines, mut listeners) = (Vec::new(), Vec::new());
        let mut roles = Vec::new();
        let mut dial_at = 0;
        for (k, v) in entries(root) {
            let (name, at) = (k.get_ref().as_ref(), k.span().start);
            let replaced = match name {
                "role" => {
                    roles = self.value(v, name, super::access::roles(&raw(v.get_ref()), name))?;
                    continue;
                }
                "dial" => {
                    dial_at = v.span().start;
                    cfg.dials = self.value(v, name, super::dial::dials(&raw(v.get_ref()), name))?;
                    continue;
                }
                "line" => ["serial", "relay"]
                    .into_iter()
                    .find(|s| root.get(*s).is_some()),
                "listen" => root.get("tcp").map(|_| "tcp"),
                _ if name == "tcp" || TOP.contains(&name) => {
                    if name == "tcp" {
                        self.not_in_tcp(v)?;
                    }
                    self.section(&mut cfg, name, v, name, &[], &[])?;
                    continue;
                }
                _ => return self.unknown(k, name, &TOP),
            };
            self.tables((name, at, v), replaced, (&mut lines, &mut listeners))?;
        }
        let (tables, listeners): (Vec<_>, Vec<ListenConfig>) = listeners.into_iter().unzip();
        if let Err((i, m)) = super::access::default_roles(&listeners, &roles) {
            let e = ValueError::new(m).value("default_role").value("tls");
            return self.bad(place(tables[i], &format!("listen[{i}]"), &e));
        }
        self.dial_roles(&cfg, &roles, dial_at)?;
        cfg.roles = roles;
        self.no_listener_for_master_lines(root, &lines, &tables)?;
        // The single-line form's listener (`[tcp]`, or none given) is already in place.
        // A file that dials its masters and names no listener opens none: the
        // default, 0.0.0.0:502 read and write for anyone, is not what it asked for.
        cfg.dial_only = !cfg.dials.is_empty() && listeners.is_empty() && root.get("tcp").is_none();
        if !listeners.is_empty() {
            cfg.listeners = listeners;
        }
        match &lines[..] {
            // Each [[line]]'s keys were checked as it was read.
            [] => self.conflict(&cfg, "")?,
            [_] => {}
            [..] => self.several_lines(&lines)?,
        }
        self.sockets(&lines, &cfg)?;
        if !lines.is_empty() {
            cfg.lines = lines.into_iter().map(|(_, line, _)| line).collect();
        }
        Ok(cfg)
    }

    /// The `[[line]]` or `[[listen]]` tables (`name`, at `at`), read into `lines` or
    /// `listeners`; refused beside the section of the single-line form they replace.
    #[allow(clippy::type_complexity)]
    fn tables<'r, 'i>(
        &mut self,
        (name, at, v): (&str, usize, &'r Spanned<DeValue<'i>>),
        replaced: Option<&str>,
        (lines, listeners): (
            &mut Vec<LineRead>,
            &mut Vec<(&'r Spanned<DeValue<'i>>, ListenConfig)>,
        ),
    ) -> Result<(), ConfigError> {
        if let Some(old) = replaced {
            let m = format!("[[{name}]] replaces [{old}]: write one form or the other");
            return self.fail(at, name, m);
        }
        let DeValue::Array(tables) = v.get_ref() else {
            return self.fail(v.span().start, name, format!("expected [[{name}]] tables"));
        };
        for (i, t) in tables.iter().enumerate() {
            let path = format!("{name}[{i}]");
            if name == "line" {
                lines.push(self.line(t, &path)?);
            } else {
                listeners.push((t, self.listener(t, &path)?));
            }
        }
        Ok(())
    }

    /// A dial's `tls.default_role` names a `[[role]]` (`dial_at`: where `[[dial]]` is).
    fn dial_roles(
        &self,
        cfg: &Config,
        roles: &[super::AccessRole],
        dial_at: usize,
    ) -> Result<(), ConfigError> {
        for (i, d) in cfg.dials.iter().enumerate() {
            let named = d.tls.as_ref().and_then(|t| t.default_role.as_ref());
            if let Some(role) = named.filter(|r| !roles.iter().any(|x| &x.name == *r)) {
                let m = format!("no [[role]] is named {role:?}");
                return self.fail(dial_at, &format!("dial[{i}].tls.default_role"), m);
            }
        }
        Ok(())
    }

    /// Several `[[line]]` tables: each but a master line lists its units, and each has
    /// its own port or address.
    fn several_lines(&self, lines: &[LineRead]) -> Result<(), ConfigError> {
        // A master line routes by its [[line.route]] tables: it serves no unit
        // of the masters'.
        let unlisted = |(_, l, units): &&LineRead| l.master.is_none() && !units;
        if let Some(i) = lines.iter().position(|l| unlisted(&l)) {
            let m = "missing: with several lines, each says which unit ids it serves";
            return self.fail(lines[i].0, &format!("line[{i}].units"), m);
        }
        // A line is known by its port or address (a reload matches lines so).
        for (i, (at, line, _)) in lines.iter().enumerate() {
            let first = lines.iter().position(|(_, l, _)| l.name() == line.name());
            if let Some(j) = first.filter(|&j| j < i) {
                let key = match line.tcp {
                    Some(_) => format!("line[{i}].tcp.address"),
                    None => format!("line[{i}].serial.path"),
                };
                let m = format!(
                    "the same as line[{j}]'s ({:?}): each line has its own port or address",
                    line.name()
                );
                let at = self.at.get(&key).copied().unwrap_or(*at);
                return self.fail(at, &key, m);
            }
        }
        Ok(())
    }

    /// When every line is a master line no Modbus/TCP master has a device to reach, so
    /// the gateway binds no listener: a `[[listen]]` or `[tcp]` there would be
    /// ignored, and is refused (a slave that connects in has its route's `listen`).
    fn no_listener_for_master_lines(
        &self,
        root: &DeTable,
        lines: &[LineRead],
        listeners: &[&Spanned<DeValue>],
    ) -> Result<(), ConfigError> {
        if lines.is_empty() || lines.iter().any(|(_, l, _)| l.master.is_none()) {
            return Ok(());
        }
        let (at, key) = match (listeners.first(), root.get_key_value("tcp")) {
            (Some(t), _) => (t.span().start, "listen[0]"),
            (None, Some((k, _))) => (k.span().start, "tcp"),
            (None, None) => return Ok(()),
        };
        let table = if key == "tcp" { "[tcp]" } else { "[[listen]]" };
        let m = format!(
            "every line is a master line (role = \"master\"): no line has a device for \
             Modbus/TCP masters to reach, so mbgate listens for none; remove {table}, or \
             add a line of slaves (a slave that connects in to a route is its `listen`)"
        );
        self.fail(at, key, m)
    }

    /// A passive route binds its address as the gateway binds its listeners (only when
    /// some line serves masters): two sockets cannot share one, so a route's `listen`
    /// on a listener's address or another route's is refused, naming the route.
    fn sockets(&self, lines: &[LineRead], cfg: &Config) -> Result<(), ConfigError> {
        let serving = lines.iter().any(|(_, l, _)| l.master.is_none());
        let listening: Vec<_> = match serving {
            true => cfg.listeners.iter().map(|l| l.tcp.listen).collect(),
            false => Vec::new(),
        };
        let mut passive = Vec::new();
        for (i, (at, line, _)) in lines.iter().enumerate() {
            let routes = line.master.iter().flat_map(|m| m.routes.iter().enumerate());
            for (j, route) in routes {
                let super::master::Peer::Listen(addr) = route.peer else {
                    continue;
                };
                let key = format!("line[{i}].route[{j}].listen");
                let taken = match listening.iter().position(|l| *l == addr) {
                    Some(k) => Some(format!("listen[{k}]'s")),
                    None => passive
                        .iter()
                        .find(|(a, _)| *a == addr)
                        .map(|(_, k)| format!("{k}'s")),
                };
                if let Some(whose) = taken {
                    let m = format!("{addr} is {whose} address too: each socket has its own");
                    return self.fail(*at, &key, m);
                }
                passive.push((addr, key));
            }
        }
        Ok(())
    }

    /// Reads the keys of `section` (of [`KEYS`]) from `v` into `cfg`; `path` is what
    /// messages call the table, `rename` the keys it calls otherwise; `skip` are keys
    /// the caller reads itself.
    fn section(
        &mut self,
        cfg: &mut Config,
        section: &str,
        v: &Spanned<DeValue>,
        path: &str,
        rename: &[(&str, &str)],
        skip: &[&str],
    ) -> Result<(), ConfigError> {
        let DeValue::Table(table) = v.get_ref() else {
            let m = raw(v.get_ref()).invalid("a table ([section])");
            return self.fail(v.span().start, path, m);
        };
        let keys: Vec<&Key> = KEYS.iter().filter(|k| k.section == section).collect();
        let mut names: Vec<&str> = keys.iter().map(|k| renamed(rename, k.name)).collect();
        for (k, v) in entries(table) {
            if skip.contains(&k.get_ref().as_ref()) {
                continue;
            }
            let full = format!("{path}.{}", k.get_ref());
            let Some(i) = names.iter().position(|n| n == k.get_ref()) else {
                names.extend(skip);
                return self.unknown(k, &full, &names);
            };
            let at = v.span().start;
            if let Err(m) = (keys[i].set)(cfg, &raw(v.get_ref())) {
                return self.fail(at, &full, m);
            }
            self.at.insert(full, at);
        }
        Ok(())
    }

    /// A `[[listen]]`: the keys of `[tcp]` (`address` for `listen`), `framing`, and
    /// who may connect and what they may do (`src/config/access/mod.rs`).
    fn listener(&mut self, v: &Spanned<DeValue>, path: &str) -> Result<ListenConfig, ConfigError> {
        let mut listener = Config::default();
        let own: Vec<&str> = super::access::LISTEN_KEYS.iter().map(|k| k.name).collect();
        self.section(&mut listener, "tcp", v, path, LISTEN_RENAMED, &own)?;
        let tcp = listener.listeners.swap_remove(0).tcp;
        // The listener's own keys, read by their declarations.
        let mut keys = Vec::new();
        if let Raw::Table(all) = raw(v.get_ref()) {
            keys = all
                .into_iter()
                .filter(|(k, _)| own.contains(&k.as_str()))
                .collect();
        }
        let read = super::access::listen(&Raw::Table(keys), path);
        let own = self.value(v, path, read)?;
        Ok(ListenConfig {
            tcp,
            framing: own.framing,
            access: own.access,
            priority: own.priority,
            transport: own.transport,
            notifications: own.notifications,
        })
    }

    /// `[tcp]` is the one listener open to all: the security keys belong in a
    /// `[[listen]]` table, and the message says so rather than "unknown key".
    fn not_in_tcp(&self, v: &Spanned<DeValue>) -> Result<(), ConfigError> {
        let DeValue::Table(t) = v.get_ref() else {
            return Ok(());
        };
        let names = entries(t).into_iter().map(|(k, _)| k);
        if let Some(k) = names
            .into_iter()
            .find(|k| super::access::is_access_key(k.get_ref()))
        {
            let name = k.get_ref();
            let m = format!(
                "{name} belongs in a [[listen]] table (write [[listen]] with address = \
                 the listen address instead of [tcp]; docs/security.md)"
            );
            return self.fail(k.span().start, &format!("tcp.{name}"), m);
        }
        Ok(())
    }

    fn bad<T>(&self, b: Bad) -> Result<T, ConfigError> {
        self.fail(b.at, &b.key, b.message)
    }

    /// `read`, the value `v` at `key` read, or its error at the place it names.
    fn value<T>(
        &self,
        v: &Spanned<DeValue>,
        key: &str,
        read: Result<T, ValueError>,
    ) -> Result<T, ConfigError> {
        read.or_else(|e| {
            let mut b = place(v, key, &e);
            // An unknown key that is no misspelling of the table's own may be
            // another table's.
            if let Some(Step::Key(name)) = e.path.last() {
                if !b.message.contains("did you mean") {
                    if let Some(elsewhere) = self.belongs(name, &b.key) {
                        b.message += &format!(" ({elsewhere})");
                    }
                }
            }
            self.bad(b)
        })
    }

    /// Refuses two keys that contradict each other, at the value of the first if the
    /// file sets it, else at the other's; `table` is the path of their section's table.
    fn conflict(&self, cfg: &Config, table: &str) -> Result<(), ConfigError> {
        let Some(c) = cfg.conflict() else {
            return Ok(());
        };
        let key = format!("{table}{}.{}", c.key.section, c.key.name);
        let other = format!("{table}{}.{}", c.other.section, c.other.name);
        // One of them is in the file: the defaults never contradict each other.
        let at = self.at.get(&key).or(self.at.get(&other)).copied();
        self.fail(at.unwrap_or(0), &key, c.message(table))
    }
}

mod line;
pub use line::LINE_TCP_KEYS;
