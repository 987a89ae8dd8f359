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

use super::raw::read_table;
use super::{table, Check, HostPort, Key, Raw, RelayConfig, Setting, ValueError, ValueKind};
use super::{Any, NonEmpty, Range, IN_FLIGHT, TIMEOUT_MS};
use crate::access::AllowList;
use std::net::SocketAddr;

table! {
    /// One `[[line.route]]` as the file gives it (docs/configuration.md "The device as
    /// master"); a [`Route`] once checked.
    ["line.route"] RouteTable ROUTE_KEYS {
        /// The unit ids sent to this slave, 1 to 255; none: every unit no other route takes
        units: RouteUnits = RouteUnits::default(), Range(1, 255, None);
        /// "HOST:PORT": mbgate connects, keeps the connection and reconnects (give address or listen)
        address: HostPort = HostPort::default(), NonEmpty("host:port of the slave");
        /// An address where mbgate listens and the slave connects in
        listen: Option<SocketAddr> = None, Any;
        /// With listen: the addresses and CIDR blocks a slave may connect from; others are closed before a byte is read (default: everyone)
        allow: Option<AllowList> = None, Any;
        /// From the request's arrival on the line to the slave's reply (also bounds a connection attempt); then 0x0B
        response_timeout_ms: u64 = RelayConfig::default().response_timeout_ms, TIMEOUT_MS;
        /// Requests outstanding on the slave's connection at once (pipelined by MBAP id)
        max_in_flight: usize = RelayConfig::default().max_in_flight, IN_FLIGHT;
    }
}

/// A route's `units = [1, 2]`: unit ids as `check` bounds them (0 is the broadcast,
/// sent on every route), none twice; empty: not given.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct RouteUnits(pub(crate) Vec<u8>);

impl Setting for RouteUnits {
    const KIND: ValueKind = ValueKind::List;
    fn read(raw: &Raw, check: &Check) -> Result<Self, ValueError> {
        let Raw::List(ids) = raw else {
            return Err("expected an array of unit ids".into());
        };
        if ids.is_empty() {
            let m = "must list at least one unit id (leave units out for the default route)";
            return Err(m.into());
        }
        let mut out = Vec::new();
        for (i, id) in ids.iter().enumerate() {
            let u = u8::read(id, check).map_err(|e| e.item(i))?;
            if out.contains(&u) {
                return Err(ValueError::new(format!("unit {u} is listed twice")).item(i));
            }
            out.push(u);
        }
        Ok(Self(out))
    }
    fn print(&self) -> String {
        let units: Vec<String> = self.0.iter().map(u8::to_string).collect();
        format!("[{}]", units.join(", "))
    }
}

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
    /// A passive route's allow list: where its slave may connect from; `None`:
    /// anywhere.
    pub allow: Option<AllowList>,
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

/// The `[[line.route]]` array `raw`; `path` is what messages call it (`line[0].route`).
pub(super) fn routes(raw: &Raw, path: &str) -> Result<Vec<Route>, ValueError> {
    let Raw::List(tables) = raw else {
        return Err("expected [[line.route]] tables".into());
    };
    let mut out: Vec<Route> = Vec::new();
    let mut default_at: Option<String> = None;
    for (i, t) in tables.iter().enumerate() {
        let here = format!("{path}[{i}]");
        let r = route(t).map_err(|e| e.item(i))?;
        for &u in &r.units {
            if let Some(j) = out.iter().position(|o| o.units.contains(&u)) {
                let m = format!("unit {u} is also in {path}[{j}]");
                return Err(ValueError::new(m).value("units").item(i));
            }
        }
        if r.units.is_empty() {
            if let Some(first) = &default_at {
                let m = format!("a second default route (no units); {first} is one");
                return Err(ValueError::new(m).item(i));
            }
            default_at = Some(here.clone());
        }
        out.push(r);
    }
    if out.is_empty() {
        return Err("a master line needs at least one route".into());
    }
    Ok(out)
}

/// One `[[line.route]]`, read by [`ROUTE_KEYS`]: exactly one of `address` and `listen`.
fn route(raw: &Raw) -> Result<Route, ValueError> {
    let (t, given) = read_table(raw, ROUTE_KEYS, "expected a table ([[line.route]])")?;
    if given.contains(&"allow") && !given.contains(&"listen") {
        let m = "only a passive route (listen) takes connections to allow; this one connects to its address";
        return Err(ValueError::new(m).value("allow"));
    }
    let peers: Vec<&str> = given
        .into_iter()
        .filter(|k| ["address", "listen"].contains(k))
        .collect();
    let peer = match (peers.as_slice(), t.listen) {
        ([], _) => return Err("missing: address (host:port of the slave) or listen".into()),
        ([_, second, ..], _) => {
            let m = "give address (connect) or listen, not both";
            return Err(ValueError::new(m).value(second));
        }
        (["listen"], Some(addr)) => Peer::Listen(addr),
        // `listen = ""` is no address.
        (["listen"], None) => {
            let m = "must not be empty (the address where mbgate listens for the slave)";
            return Err(ValueError::new(m).value("listen"));
        }
        _ => Peer::Connect(t.address.0),
    };
    Ok(Route {
        units: t.units.0,
        peer,
        response_timeout_ms: t.response_timeout_ms,
        max_in_flight: t.max_in_flight,
        allow: t.allow,
    })
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
            Peer::Connect(a) => out += &format!("address = {}\n", HostPort(a.clone()).print()),
            Peer::Listen(a) => out += &format!("listen = {}\n", a.print()),
        }
        if r.allow.is_some() {
            out += &format!("allow = {}\n", r.allow.print());
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
            allow: None,
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
        let read = |s: &str| HostPort::read(&Raw::Str(s.into()), &Check::Any);
        assert!(read("plc.local:502").is_ok());
        assert!(read("[::1]:502").is_ok());
        assert!(read("plc.local").is_err());
        assert!(read(":502").is_err());
        assert!(read("h:0").is_err());
    }
}
