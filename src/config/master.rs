//! A line whose device is the master (docs/design.md §4.2): `role = "master"` on a
//! `[[line]]` and its `[[line.route]]` tables, read, checked and printed here so the
//! rest of the configuration code only carries one field for it.
//!
//! ```toml
//! [[line]]
//! role = "master"
//! serial = { path = "/dev/ttyUSB0", framing = "mbap" }
//!
//! [[line.route]]              # units 1 and 2 go to this Modbus/TCP slave
//! units = [1, 2]
//! address = "192.168.0.20:502"
//! response_timeout_ms = 1000
//! max_in_flight = 1
//!
//! [[line.route]]              # no units: the default route
//! listen = "0.0.0.0:5021"     # passive: the slave connects in
//! ```

use super::raw::{bad, entries, raw_value, Bad};
use super::{Check, Setting};
use std::net::SocketAddr;
use toml::de::{DeTable, DeValue};
use toml::Spanned;

/// The keys of a `[[line.route]]` table.
pub(crate) const ROUTE_KEYS: [&str; 5] = [
    "units",
    "address",
    "listen",
    "response_timeout_ms",
    "max_in_flight",
];

/// Where a route's slave is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Peer {
    /// mbgate connects to this `host:port` (active), and reconnects when it is lost.
    Connect(String),
    /// mbgate listens here and the slave connects in (passive).
    Listen(SocketAddr),
}

impl std::fmt::Display for Peer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Peer::Connect(a) => write!(f, "{a}"),
            Peer::Listen(a) => write!(f, "slaves connecting to {a}"),
        }
    }
}

/// One `[[line.route]]`: the unit ids it takes (none: the default route) and its slave.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Route {
    /// The unit ids sent this way; empty: every unit no other route takes.
    pub units: Vec<u8>,
    /// Where the slave is.
    pub peer: Peer,
    /// From the request's arrival on the serial line to the slave's reply; also bounds
    /// a connection attempt.
    pub response_timeout_ms: u64,
    /// Requests outstanding on the slave's connection at once (pipelined by MBAP id).
    pub max_in_flight: usize,
}

/// What a master line adds to the line: its routes, in the order of the file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MasterLine {
    /// The routes; a request takes the first that lists its unit, else the default.
    pub routes: Vec<Route>,
}

impl MasterLine {
    /// The route a unit id goes to: the one that lists it, else the default route.
    pub fn route_for(&self, unit: u8) -> Option<usize> {
        let listed = self.routes.iter().position(|r| r.units.contains(&unit));
        listed.or_else(|| self.routes.iter().position(|r| r.units.is_empty()))
    }
}

/// `role = "slave" | "master"`: true for a master line.
pub(super) fn role(v: &Spanned<DeValue>, key: &str) -> Result<bool, Bad> {
    match v.get_ref() {
        DeValue::String(s) if s == "master" => Ok(true),
        DeValue::String(s) if s == "slave" => Ok(false),
        DeValue::String(s) => bad(
            v.span().start,
            key,
            format!(
                "invalid value {:?}; expected one of slave, master",
                s.as_ref()
            ),
        ),
        _ => bad(
            v.span().start,
            key,
            "expected a string, one of slave, master",
        ),
    }
}

/// The `[[line.route]]` array at `v`; `path` is `line[0].route`.
pub(super) fn routes(v: &Spanned<DeValue>, path: &str) -> Result<Vec<Route>, Bad> {
    let DeValue::Array(tables) = v.get_ref() else {
        return bad(v.span().start, path, "expected [[line.route]] tables");
    };
    let mut out: Vec<Route> = Vec::new();
    let mut default_at: Option<String> = None;
    for (i, t) in tables.iter().enumerate() {
        let here = format!("{path}[{i}]");
        let DeValue::Table(table) = t.get_ref() else {
            return bad(t.span().start, &here, "expected a table ([[line.route]])");
        };
        let r = route(table, t.span().start, &here)?;
        for &u in &r.units {
            if let Some(j) = out.iter().position(|o| o.units.contains(&u)) {
                let at = table
                    .get("units")
                    .map_or(t.span().start, |v| v.span().start);
                return bad(
                    at,
                    &format!("{here}.units"),
                    format!("unit {u} is also in {path}[{j}]"),
                );
            }
        }
        if r.units.is_empty() {
            if let Some(first) = &default_at {
                return bad(
                    t.span().start,
                    &here,
                    format!("a second default route (no units); {first} is one"),
                );
            }
            default_at = Some(here.clone());
        }
        out.push(r);
    }
    if out.is_empty() {
        return bad(
            v.span().start,
            path,
            "a master line needs at least one route",
        );
    }
    Ok(out)
}

fn route(table: &DeTable, start: usize, path: &str) -> Result<Route, Bad> {
    let mut r = Route {
        units: Vec::new(),
        peer: Peer::Connect(String::new()),
        response_timeout_ms: 1000,
        max_in_flight: 1,
    };
    let mut peer = None;
    for (k, v) in entries(table) {
        let key = format!("{path}.{}", k.get_ref());
        let at = v.span().start;
        let raw = || raw_value(v.get_ref());
        let given = match k.get_ref().as_ref() {
            "units" => {
                r.units = units(v, &key)?;
                None
            }
            "address" => {
                let s = String::read(&raw(), &Check::NonEmpty("host:port of the slave"))
                    .or_else(|m| bad(at, &key, m))?;
                check_host_port(&s).or_else(|m| bad(at, &key, m))?;
                Some(Peer::Connect(s))
            }
            "listen" => {
                let a = SocketAddr::read(&raw(), &Check::Any).or_else(|m| bad(at, &key, m))?;
                Some(Peer::Listen(a))
            }
            "response_timeout_ms" => {
                r.response_timeout_ms = u64::read(&raw(), &Check::Range(1, 600_000, None))
                    .or_else(|m| bad(at, &key, m))?;
                None
            }
            "max_in_flight" => {
                r.max_in_flight = usize::read(&raw(), &Check::Range(1, 255, None))
                    .or_else(|m| bad(at, &key, m))?;
                None
            }
            _ => {
                return bad(
                    k.span().start,
                    &key,
                    format!("unknown key; expected one of {}", ROUTE_KEYS.join(", ")),
                )
            }
        };
        if let Some(p) = given {
            if peer.is_some() {
                return bad(at, &key, "give address (connect) or listen, not both");
            }
            peer = Some(p);
        }
    }
    r.peer = match peer {
        Some(p) => p,
        None => {
            return bad(
                start,
                path,
                "missing: address (host:port of the slave) or listen",
            )
        }
    };
    Ok(r)
}

/// `units = [1, 2]`: unit ids 1..=255 (0 is the broadcast, sent on every route).
fn units(v: &Spanned<DeValue>, key: &str) -> Result<Vec<u8>, Bad> {
    let DeValue::Array(ids) = v.get_ref() else {
        return bad(v.span().start, key, "expected an array of unit ids");
    };
    if ids.is_empty() {
        return bad(
            v.span().start,
            key,
            "must list at least one unit id (leave units out for the default route)",
        );
    }
    let mut out = Vec::new();
    for id in ids.iter() {
        let raw = raw_value(id.get_ref());
        let u = u8::read(&raw, &Check::Range(1, 255, None))
            .or_else(|m| bad(id.span().start, key, m))?;
        if out.contains(&u) {
            return bad(id.span().start, key, format!("unit {u} is listed twice"));
        }
        out.push(u);
    }
    Ok(out)
}

/// `host:port`, the port a number: resolved when connecting, so a name works too.
fn check_host_port(s: &str) -> Result<(), String> {
    let ok = s
        .rsplit_once(':')
        .is_some_and(|(host, port)| !host.is_empty() && port.parse::<u16>().is_ok_and(|p| p > 0));
    if ok {
        Ok(())
    } else {
        Err(format!(
            "expected host:port, e.g. 192.168.0.20:502, got {s:?}"
        ))
    }
}

/// The master line as the `[[line]]` form prints it (`mbgate check-config`), after
/// its `serial` table; `parse` reads it back to the same.
pub(crate) fn to_toml(m: &MasterLine) -> String {
    let mut out = String::new();
    for r in &m.routes {
        out += "\n[[line.route]]\n";
        if !r.units.is_empty() {
            let units: Vec<String> = r.units.iter().map(u8::to_string).collect();
            out += &format!("units = [{}]\n", units.join(", "));
        }
        match &r.peer {
            Peer::Connect(a) => out += &format!("address = {}\n", a.print()),
            Peer::Listen(a) => out += &format!("listen = {}\n", a.print()),
        }
        out += &format!("response_timeout_ms = {}\n", r.response_timeout_ms);
        out += &format!("max_in_flight = {}\n", r.max_in_flight);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn route(units: &[u8]) -> Route {
        Route {
            units: units.to_vec(),
            peer: Peer::Connect("h:1".into()),
            response_timeout_ms: 1000,
            max_in_flight: 1,
        }
    }

    #[test]
    fn listed_units_then_the_default() {
        let m = MasterLine {
            routes: vec![route(&[1, 2]), route(&[]), route(&[3])],
        };
        assert_eq!(m.route_for(2), Some(0));
        assert_eq!(m.route_for(3), Some(2));
        assert_eq!(m.route_for(9), Some(1));
        let m = MasterLine {
            routes: vec![route(&[1])],
        };
        assert_eq!(m.route_for(9), None);
    }

    #[test]
    fn host_port() {
        assert!(check_host_port("plc.local:502").is_ok());
        assert!(check_host_port("[::1]:502").is_ok());
        assert!(check_host_port("plc.local").is_err());
        assert!(check_host_port(":502").is_err());
        assert!(check_host_port("h:0").is_err());
    }
}
