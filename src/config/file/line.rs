//! Reading a `[[line]]` of the file (docs/design.md §4.1, §4.2): its units and
//! their remapping, each unit on one line only; its device on a serial port or at a
//! TCP address; its role, and a master line's routes and the relay keys it refuses.

use super::{raw, FileReader, LineRead};
use crate::config::raw::{entries, read_table};
use crate::config::{
    table, Check, Config, ConfigError, Framing, HostPort, Key, LineConfig, LineRole, Setting,
    TlsDevice, Units, ValueError, KEYS,
};
use crate::config::{Any, NonEmpty};
use std::collections::{BTreeMap, BTreeSet};
use toml::de::DeValue;
use toml::Spanned;

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

/// A `[[line]]`'s keys as read, before they are checked together.
#[derive(Default)]
struct LineKeysRead {
    /// Its `serial` and `relay` sections, as the single-line form's.
    line: Config,
    /// It gave `units` or `remap`.
    listed: bool,
    units: Units,
    tcp: Option<String>,
    tcp_tls: Option<TlsDevice>,
    /// Where `serial` is.
    serial_at: Option<usize>,
    /// A master line, and where `role` is.
    role: Option<(bool, usize)>,
    /// The `[[line.route]]` tables, and where.
    routes: Option<(Vec<crate::config::master::Route>, usize)>,
    /// The `[[line.unit]]` tables, and where.
    unit_tables: (crate::config::unit::UnitTables, Option<usize>),
}

impl FileReader<'_> {
    /// One `[[line]]` at `v`; `path` is what messages call it (`line[0]`).
    pub(super) fn line(
        &mut self,
        v: &Spanned<DeValue>,
        path: &str,
    ) -> Result<LineRead, ConfigError> {
        let DeValue::Table(table) = v.get_ref() else {
            let m = raw(v.get_ref()).invalid("a table ([[line]])");
            return self.fail(v.span().start, path, m);
        };
        let mut r = LineKeysRead::default();
        for (k, item) in entries(table) {
            let full = format!("{path}.{}", k.get_ref());
            self.line_key(&mut r, k, item, &full)?;
        }
        if let (Some(_), Some(at)) = (&r.tcp, r.serial_at) {
            let m = "a line's device is a serial port or a TCP address: give `serial` or `tcp`, not both";
            return self.fail(at, &format!("{path}.serial"), m);
        }
        // A key that means nothing on a master line is named as such, before what it
        // would conflict with on a line of slaves.
        if matches!(r.role, Some((true, _))) {
            self.master_line_keys(path)?;
        }
        self.conflict(&r.line, &format!("{path}."))?;
        let master = self.master_line(&mut r, v, path)?;
        let line = LineConfig {
            units: r.units,
            tcp: r.tcp,
            tcp_tls: r.tcp_tls,
            unit_tables: r.unit_tables.0,
            master,
            ..r.line.lines.swap_remove(0)
        };
        Ok((v.span().start, line, r.listed))
    }

    /// One key `k` of a `[[line]]` (`full`: its path) into `r`.
    fn line_key(
        &mut self,
        r: &mut LineKeysRead,
        k: &Spanned<std::borrow::Cow<str>>,
        item: &Spanned<DeValue>,
        full: &str,
    ) -> Result<(), ConfigError> {
        match k.get_ref().as_ref() {
            "units" => {
                r.units.ids = self.units(item, full)?;
                r.listed = true;
            }
            "remap" => {
                r.units.remap = self.remap(item, full)?;
                r.listed = true;
            }
            "tcp" => {
                let (address, tls) = self.line_tcp(&mut r.line, item, full)?;
                r.tcp = Some(address);
                r.tcp_tls = tls;
            }
            "role" => {
                let read = LineRole::read(&raw(item.get_ref()), &Check::Any);
                let master = self.value(item, full, read)? == LineRole::Master;
                r.role = Some((master, k.span().start));
            }
            "unit" => {
                let read = crate::config::unit::tables(&raw(item.get_ref()), full);
                r.unit_tables = (self.value(item, full, read)?, Some(k.span().start));
            }
            "route" => {
                let read = crate::config::master::routes(&raw(item.get_ref()), full);
                r.routes = Some((self.value(item, full, read)?, k.span().start));
            }
            name @ ("serial" | "relay") => {
                if name == "serial" {
                    r.serial_at = Some(k.span().start);
                }
                self.section(&mut r.line, name, item, full, &[], &[])?
            }
            _ => return self.unknown(k, full, &LINE),
        }
        Ok(())
    }

    /// A line with `role = "master"` and its `[[line.route]]` tables: its routes, and
    /// none of a line of slaves' keys (`units`, `remap`, `tcp`, `[[line.unit]]`); routes
    /// without the role are refused.
    fn master_line(
        &self,
        r: &mut LineKeysRead,
        v: &Spanned<DeValue>,
        path: &str,
    ) -> Result<Option<crate::config::master::MasterLine>, ConfigError> {
        match (r.role, r.routes.take()) {
            (Some((true, _)), Some((routes, _))) => {
                if r.listed {
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
                if let Some(at) = r.tcp.as_ref().and(r.serial_at.or(Some(v.span().start))) {
                    let m = "a master line's device is on a serial port, not on TCP";
                    return self.fail(at, &format!("{path}.tcp"), m);
                }
                if let Some(at) = r.unit_tables.1 {
                    let m = "a master line has no units of its own: give timeouts in its [[line.route]] tables";
                    return self.fail(at, &format!("{path}.unit"), m);
                }
                return Ok(Some(crate::config::master::MasterLine { routes }));
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
        Ok(None)
    }

    /// A master line's `serial` and `relay` tables hold only the keys a master line
    /// uses (declared `master` in `settings!`). The others are the relay's: a
    /// response timeout, retries, the queue; the gap before a request, an echo to drop,
    /// a transmitter the gateway switches. A master line has none of these, so such a
    /// key would be silently ignored, and a reload could not apply it.
    fn master_line_keys(&self, path: &str) -> Result<(), ConfigError> {
        let tables = KEYS
            .iter()
            .filter(|k| matches!(k.section, "serial" | "relay"));
        for key in tables.filter(|k| !k.master) {
            let full = format!("{path}.{}.{}", key.section, key.name);
            let Some(&at) = self.at.get(&full) else {
                continue;
            };
            let mut m = if key.section == "serial" {
                "means nothing on a master line (the device is the master: the gateway \
                 only answers it, with no gap, echo or transmitter of its own to keep)"
            } else {
                "means nothing on a master line (the device is the master: no request \
                 of a Modbus/TCP master is queued or timed on it)"
            }
            .to_owned();
            if crate::config::master::ROUTE_KEYS
                .iter()
                .any(|k| k.name == key.name)
            {
                m += &format!("; give {} in its [[line.route]] tables", key.name);
            } else if key.name.starts_with("direction") {
                m += "; for RS-485 let the adapter or the kernel switch it (rs485 = true)";
            } else {
                let used: Vec<&str> = KEYS
                    .iter()
                    .filter(|k| k.section == key.section && k.master)
                    .map(|k| k.name)
                    .collect();
                m += &format!(
                    "; its [line.{}] takes only {}",
                    key.section,
                    used.join(", ")
                );
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
    ) -> Result<(String, Option<TlsDevice>), ConfigError> {
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
        line.lines[0].serial.framing = t.framing;
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
