//! Reading a configuration file: toml gives the position of every key and value
//! (`DeTable`), each key is checked by its declaration in [`KEYS`], and every error
//! names file, line, column and key: `x.toml:7:13: serial.baud_rate: must be between
//! 50 and 4000000, got 10`. Both forms of docs/design.md §4 and §4.1 are read.

use super::error::{line_col, syntax_error, ConfigError};
use super::raw::{entries, place, raw_value as raw, read_table, suggest, Bad, Raw};
use super::{
    table, Check, Config, Framing, HostPort, Key, LineConfig, LineRole, ListenConfig,
    ListenFraming, Setting, Step, TlsDevice, Units, ValueError, KEYS,
};
use super::{Any, NonEmpty};
use std::borrow::Cow;
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::Path;
use toml::de::{DeTable, DeValue};
use toml::Spanned;

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
    let root = DeTable::parse(text).map_err(|e| syntax_error(text, origin, &e))?;
    let lines_form = ["line", "listen"]
        .iter()
        .any(|t| root.get_ref().get(*t).is_some());
    Reader {
        text,
        origin,
        at: HashMap::new(),
        units: HashMap::new(),
        lines_form,
    }
    .read(root.get_ref())
}

/// The top-level tables; `line` and `listen` are arrays of tables (docs/design.md §4.1).
const TOP: [&str; 10] = [
    "serial", "tcp", "relay", "log", "metrics", "capture", "control", "line", "listen", "role",
];
/// The keys of a `[[line]]` table.
const LINE: [&str; 8] = [
    "units", "remap", "serial", "tcp", "relay", "role", "route", "unit",
];
table! {
    /// A line's `tcp` table: its device on the network (docs/network-devices.md).
    ["line.tcp"] LineTcpTable LINE_TCP_KEYS {
        /// "HOST:PORT" of the device (a Modbus/TCP slave, or a serial device server in raw TCP mode); required
        address: HostPort = HostPort::default(), NonEmpty("host:port");
        /// How frames are carried to it: mbap, rtu or ascii
        framing: Framing = Framing::Mbap, Any;
        /// The device speaks TLS: { cert, key, device_ca, server_name }
        tls: Option<TlsDevice> = None, Any;
    }
}
/// In a `[[listen]]` table, the `[tcp]` key `listen` is called `address`.
pub(super) const LISTEN_RENAMED: &[(&str, &str)] = &[("address", "listen")];

/// What a table calls key `name` of [`KEYS`], given its pairs of (in the file, in
/// [`KEYS`]).
pub(super) fn renamed<'a>(rename: &[(&'a str, &'a str)], name: &'a str) -> &'a str {
    let found = rename.iter().find(|(_, key)| *key == name);
    found.map_or(name, |(file, _)| file)
}

struct Reader<'t> {
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

impl Reader<'_> {
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
        for (k, v) in entries(root) {
            let (name, at) = (k.get_ref().as_ref(), k.span().start);
            let replaced = match name {
                "role" => {
                    roles = self.value(v, name, super::access::roles(&raw(v.get_ref()), name))?;
                    continue;
                }
                "tcp" => {
                    self.not_in_tcp(v)?;
                    self.section(&mut cfg, name, v, name, &[], &[])?;
                    continue;
                }
                "line" => ["serial", "relay"]
                    .into_iter()
                    .find(|s| root.get(*s).is_some()),
                "listen" => root.get("tcp").map(|_| "tcp"),
                _ if TOP.contains(&name) => {
                    self.section(&mut cfg, name, v, name, &[], &[])?;
                    continue;
                }
                _ => return self.unknown(k, name, &TOP),
            };
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
        }
        let (tables, listeners): (Vec<_>, Vec<ListenConfig>) = listeners.into_iter().unzip();
        if let Err((i, m)) = super::access::default_roles(&listeners, &roles) {
            let e = ValueError::new(m).value("default_role").value("tls");
            return self.bad(place(tables[i], &format!("listen[{i}]"), &e));
        }
        cfg.roles = roles;
        self.no_listener_for_master_lines(root, &lines, &tables)?;
        match &listeners[..] {
            [] => {}
            // One Modbus/TCP listener open to all is the old form's [tcp].
            [one]
                if one.framing == ListenFraming::Mbap
                    && one.access.is_open()
                    && one.priority == 0 =>
            {
                cfg.tcp = one.tcp.clone()
            }
            [first, ..] => {
                cfg.tcp = first.tcp.clone();
                cfg.listeners = listeners;
            }
        }
        let old_form = match &lines[..] {
            [] => {
                self.conflict(&cfg, "")?;
                true
            }
            // One serial line serving every unit is the old form's [serial] and [relay],
            // unless its units have settings of their own, which only a [[line]] says;
            // so is a master line (its routes say where each unit goes).
            [(_, line, _)]
                if line.tcp.is_none() && line.units.every() && line.unit_tables.is_empty() =>
            {
                (cfg.serial, cfg.relay) = (line.serial.clone(), line.relay.clone());
                cfg.master = line.master.clone();
                true
            }
            [_] => false,
            [..] => {
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
                false
            }
        };
        self.sockets(&lines, &cfg)?;
        if !old_form {
            // The first line's settings stand for the gateway's where one is asked for.
            (cfg.serial, cfg.relay) = (lines[0].1.serial.clone(), lines[0].1.relay.clone());
            cfg.lines = lines.into_iter().map(|(_, line, _)| line).collect();
        }
        Ok(cfg)
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
            true => cfg.listeners().iter().map(|l| l.tcp.listen).collect(),
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
    /// who may connect and what they may do (`src/config/access.rs`).
    fn listener(&mut self, v: &Spanned<DeValue>, path: &str) -> Result<ListenConfig, ConfigError> {
        let mut listener = Config::default();
        let own: Vec<&str> = super::access::LISTEN_KEYS.iter().map(|k| k.name).collect();
        self.section(&mut listener, "tcp", v, path, LISTEN_RENAMED, &own)?;
        // The listener's own keys, read by their declarations.
        let mut keys = Vec::new();
        if let Raw::Table(all) = raw(v.get_ref()) {
            keys = all
                .into_iter()
                .filter(|(k, _)| own.contains(&k.as_str()))
                .collect();
        }
        let read = super::access::listen(&Raw::Table(keys), path);
        let (access, framing, priority) = self.value(v, path, read)?;
        Ok(ListenConfig {
            tcp: listener.tcp,
            framing,
            access,
            priority,
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

    fn line(&mut self, v: &Spanned<DeValue>, path: &str) -> Result<LineRead, ConfigError> {
        let DeValue::Table(table) = v.get_ref() else {
            let m = raw(v.get_ref()).invalid("a table ([[line]])");
            return self.fail(v.span().start, path, m);
        };
        let (mut line, mut listed) = (Config::default(), false);
        let (mut units, mut tcp, mut serial_at) = (Units::default(), None, None);
        let (mut role, mut routes, mut tcp_tls) = (None, None, None);
        let mut unit_tables = (super::unit::UnitTables::default(), None);
        for (k, item) in entries(table) {
            let full = format!("{path}.{}", k.get_ref());
            match k.get_ref().as_ref() {
                "units" => {
                    units.ids = self.units(item, &full)?;
                    listed = true;
                }
                "remap" => {
                    units.remap = self.remap(item, &full)?;
                    listed = true;
                }
                "tcp" => {
                    let (address, tls) = self.line_tcp(&mut line, item, &full)?;
                    tcp = Some(address);
                    tcp_tls = tls;
                }
                "role" => {
                    let read = LineRole::read(&raw(item.get_ref()), &Check::Any);
                    let master = self.value(item, &full, read)? == LineRole::Master;
                    role = Some((master, k.span().start));
                }
                "unit" => {
                    let read = super::unit::tables(&raw(item.get_ref()), &full);
                    unit_tables = (self.value(item, &full, read)?, Some(k.span().start));
                }
                "route" => {
                    let read = super::master::routes(&raw(item.get_ref()), &full);
                    routes = Some((self.value(item, &full, read)?, k.span().start));
                }
                name @ ("serial" | "relay") => {
                    if name == "serial" {
                        serial_at = Some(k.span().start);
                    }
                    self.section(&mut line, name, item, &full, &[], &[])?
                }
                _ => return self.unknown(k, &full, &LINE),
            }
        }
        if let (Some(_), Some(at)) = (&tcp, serial_at) {
            let m = "a line's device is a serial port or a TCP address: give `serial` or `tcp`, not both";
            return self.fail(at, &format!("{path}.serial"), m);
        }
        self.conflict(&line, &format!("{path}."))?;
        let mut master = None;
        match (role, routes) {
            (Some((true, _)), Some((routes, _))) => {
                if listed {
                    let key = format!("{path}.units");
                    let key = if self.at.contains_key(&key) {
                        key
                    } else {
                        format!("{path}.remap")
                    };
                    let at = self.at.get(&key).copied().unwrap_or(v.span().start);
                    let m = "a master line routes by the units of its [[line.route]] tables";
                    return self.fail(at, &key, m);
                }
                if let Some(at) = tcp.as_ref().and(serial_at.or(Some(v.span().start))) {
                    let m = "a master line's device is on a serial port, not on TCP";
                    return self.fail(at, &format!("{path}.tcp"), m);
                }
                if let Some(at) = unit_tables.1 {
                    let m = "a master line has no units of its own: give timeouts in its [[line.route]] tables";
                    return self.fail(at, &format!("{path}.unit"), m);
                }
                self.master_relay(path)?;
                master = Some(super::master::MasterLine { routes });
            }
            (Some((true, at)), None) => {
                let m = "a master line needs [[line.route]] tables (where its requests go)";
                return self.fail(at, &format!("{path}.role"), m);
            }
            (_, Some((_, at))) => {
                let m = "routes belong to a master line: add role = \"master\"";
                return self.fail(at, &format!("{path}.route"), m);
            }
            (_, None) => {}
        }
        let line = LineConfig {
            units,
            serial: line.serial,
            tcp,
            tcp_tls,
            relay: line.relay,
            unit_tables: unit_tables.0,
            master,
        };
        Ok((v.span().start, line, listed))
    }

    /// A master line's `relay` table holds only the keys a master line uses (declared
    /// `master` in `settings!`): the others (a response timeout, retries, the queue...)
    /// are the relay's, which a master line has not, and a reload could not apply them.
    fn master_relay(&self, path: &str) -> Result<(), ConfigError> {
        let relay = KEYS.iter().filter(|k| k.section == "relay");
        for key in relay.filter(|k| !k.master) {
            let full = format!("{path}.relay.{}", key.name);
            let Some(&at) = self.at.get(&full) else {
                continue;
            };
            let mut m = "means nothing on a master line (the device is the master: no request \
                         of a Modbus/TCP master is queued or timed on it)"
                .to_owned();
            if super::master::ROUTE_KEYS.iter().any(|k| k.name == key.name) {
                m += &format!("; give {} in its [[line.route]] tables", key.name);
            } else {
                let used: Vec<&str> = KEYS
                    .iter()
                    .filter(|k| k.section == "relay" && k.master)
                    .map(|k| k.name)
                    .collect();
                m += &format!("; its [line.relay] takes only {}", used.join(", "));
            }
            return self.fail(at, &full, m);
        }
        Ok(())
    }

    /// A line's `tcp` table, read by [`LINE_TCP_KEYS`]: `address` required.
    fn line_tcp(
        &mut self,
        line: &mut Config,
        v: &Spanned<DeValue>,
        path: &str,
    ) -> Result<(String, Option<super::TlsDevice>), ConfigError> {
        let value = raw(v.get_ref());
        let not_table = value.invalid("a table (address, framing)").message;
        let (t, given) = self.value(v, path, read_table(&value, LINE_TCP_KEYS, &not_table))?;
        let address = format!("{path}.address");
        let DeValue::Table(table) = v.get_ref() else {
            unreachable!("read as a table")
        };
        let Some(at) = table.get("address").filter(|_| given.contains(&"address")) else {
            return self.fail(v.span().start, &address, "missing: the device's host:port");
        };
        // Where it is, for a second line on the same address.
        self.at.insert(address, at.span().start);
        line.serial.framing = t.framing;
        Ok((t.address.0, t.tls))
    }

    /// `units = [1, 2, "10-20", ...]`: unit ids and ranges, each on one line only.
    fn units(&mut self, v: &Spanned<DeValue>, path: &str) -> Result<BTreeSet<u8>, ConfigError> {
        let at = v.span().start;
        self.at.insert(path.to_owned(), at);
        let ids = match v.get_ref() {
            DeValue::Array(ids) if ids.is_empty() => {
                return self.fail(at, path, "must list at least one unit id")
            }
            DeValue::Array(ids) => ids,
            other => return self.fail(at, path, raw(other).invalid("an array of unit ids")),
        };
        let mut set = BTreeSet::new();
        for id in ids.iter() {
            let at = id.span().start;
            let (first, last) = match id.get_ref() {
                DeValue::String(range) => unit_range(range).or_else(|m| self.fail(at, path, m))?,
                other => {
                    let unit = u8::read(&raw(other), &Check::Range(1, 255, None));
                    let unit = unit.or_else(|m| self.fail(at, path, m))?;
                    (unit, unit)
                }
            };
            for unit in first..=last {
                self.claim(unit, at, path)?;
                set.insert(unit);
            }
        }
        Ok(set)
    }

    /// `remap = { 11 = 1 }`: the master's unit 11 is unit 1 on this line.
    fn remap(&mut self, v: &Spanned<DeValue>, path: &str) -> Result<BTreeMap<u8, u8>, ConfigError> {
        let DeValue::Table(table) = v.get_ref() else {
            let m = raw(v.get_ref()).invalid("a table of unit = unit on the line");
            return self.fail(v.span().start, path, m);
        };
        let mut map = BTreeMap::new();
        for (k, item) in entries(table) {
            let at = k.span().start;
            let unit = k.get_ref().parse::<u8>().ok().filter(|u| *u >= 1);
            let Some(unit) = unit else {
                let m = format!("{:?} is not a unit id (1 to 255)", k.get_ref());
                return self.fail(at, path, m);
            };
            self.claim(unit, at, path)?;
            let on_line = u8::read(&raw(item.get_ref()), &Check::Range(0, 255, None));
            let on_line = on_line.or_else(|m| self.fail(item.span().start, path, m))?;
            map.insert(unit, on_line);
        }
        Ok(map)
    }

    /// Gives `unit` to the line at `path`, unless another line (or this one) has it.
    fn claim(&mut self, unit: u8, at: usize, path: &str) -> Result<(), ConfigError> {
        if let Some(other) = self.units.insert(unit, path.to_owned()) {
            return self.fail(at, path, format!("unit {unit} is also in {other}"));
        }
        Ok(())
    }

    /// Refuses two keys that contradict each other, at the value of the first if the
    /// file sets it, else at the other's; `table` is the path of their section's table.
    fn conflict(&self, cfg: &Config, table: &str) -> Result<(), ConfigError> {
        let Some(c) = cfg.conflict() else {
            return Ok(());
        };
        let prefix = format!("{table}{}.", c.key.section);
        let key = format!("{prefix}{}", c.key.name);
        let other = format!("{prefix}{}", c.other.name);
        // One of them is in the file: the defaults never contradict each other.
        let at = self.at.get(&key).or(self.at.get(&other)).copied();
        self.fail(at.unwrap_or(0), &key, c.message(&prefix))
    }
}

/// `"10-20"`: the units 10 to 20.
fn unit_range(s: &str) -> Result<(u8, u8), ValueError> {
    let bad = || format!("expected a unit id or a range like \"10-20\", got {s:?}");
    let (a, b) = s.split_once('-').ok_or_else(bad)?;
    let unit = |x: &str| x.trim().parse::<u8>().ok().filter(|u| *u >= 1);
    match (unit(a), unit(b)) {
        (Some(a), Some(b)) if a <= b => Ok((a, b)),
        (Some(_), Some(_)) => Err(format!("the range {s:?} is empty").into()),
        _ => Err(bad().into()),
    }
}
