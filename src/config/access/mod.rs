//! The security keys of the file (docs/security.md): on a `[[listen]]` its `allow`
//! list, `read_only`, `write` rules and `tls` table; the `[[role]]` tables; a TCP
//! line's `tls` table. Read, checked and printed here, so the rest of the
//! configuration code carries one field for each.
//!
//! ```toml
//! [[listen]]
//! address = "0.0.0.0:802"
//! allow = ["10.0.0.0/24", "2001:db8::/32"]
//! tls = { cert = "/etc/mbgate/tls/gateway.pem", key = "/etc/mbgate/tls/gateway.key",
//!         client_ca = "/etc/mbgate/tls/ca.pem" }
//!
//! [[role]]
//! name = "operator"
//! write = [{ units = [1], functions = [6, 16], addresses = "100-199" }]
//!
//! [[role]]
//! name = "viewer"
//! read_only = true
//! ```

use super::raw::read_table;
use super::{table, Check, Key, ListenFraming, Raw, Setting, Transport, ValueError, ValueKind};
use super::{Any, NonEmpty, Range};
use crate::access::{AllowList, Net, Policy, UnitSet, WriteRule};
use crate::frame::function::FunctionCode;
use std::path::PathBuf;

/// The most priority classes there are: `priority` is 0 (the default, the lowest) to
/// this.
pub(crate) const PRIORITY_MAX: u8 = 7;
/// A listener's or a role's `priority`.
pub(super) const PRIORITY: Check = Range(
    0,
    PRIORITY_MAX as i128,
    Some("0 (the default, the lowest) to 7"),
);

table! {
    /// The keys a `[[listen]]` has beyond those of `[tcp]` (docs/configuration.md
    /// "Several lines and listeners", docs/security.md).
    ["listen"] ListenTable LISTEN_KEYS {
        /// How its masters frame their requests: mbap (Modbus/TCP) or rtu (RTU over TCP)
        framing: ListenFraming = ListenFraming::Mbap, Any;
        /// tcp (connections), or udp (one MBAP request a datagram, answered to its source)
        transport: Transport = Transport::Tcp, Any;
        /// The addresses and CIDR blocks whose masters are taken; none: everyone
        allow: Option<AllowList> = None, Any;
        /// Every request that may act on a device is answered 0x01
        read_only: bool = false, Any;
        /// Rules { units, functions, addresses }: only the writes one of them matches pass
        write: WriteRules = WriteRules::default(), Any;
        /// Modbus/TCP Security: { cert, key, client_ca, default_role, handshake_timeout_ms }
        tls: Option<TlsListen> = None, Any;
        /// Its masters' priority class on every line, 0 (the lowest) to 7
        priority: u8 = 0, PRIORITY;
        /// UDP only: its sources get the lines' notifications, each for 1 s after its last request
        notifications: bool = false, Any;
    }
}

table! {
    /// A listener's `tls` table (docs/security.md "Modbus/TCP Security").
    ["listen.tls"] TlsListenTable LISTEN_TLS_KEYS {
        /// The gateway's certificate chain (PEM), leaf first; required
        cert: String = String::new(), NonEmpty("the gateway's certificate, PEM");
        /// Its private key (PEM: PKCS#8, PKCS#1 or SEC1); required
        key: String = String::new(), NonEmpty("the gateway's private key, PEM");
        /// The CA certificates (PEM) a master's certificate must chain to; required
        client_ca: String = String::new(), NonEmpty("the CA certificates masters' certificates chain to, PEM");
        /// The role of a certificate that carries none; none: such a master is refused
        default_role: String = String::new(), NonEmpty("a [[role]] name");
        /// The most a TLS handshake may take, from the accept
        handshake_timeout_ms: u64 = 10_000, Range(100, 600_000, None);
    }
}

table! {
    /// A `[[role]]` (docs/security.md "What a master may do").
    ["role"] RoleTable ROLE_KEYS {
        /// The role as a client certificate carries it (the Modbus role extension); required
        name: String = String::new(), NonEmpty("the role's name");
        /// A master with this role may not act on a device
        read_only: bool = false, Any;
        /// The writes a master with this role may make, as a listener's
        write: WriteRules = WriteRules::default(), Any;
        /// The priority class of a master with this role, over its listener's
        priority: u8 = 0, PRIORITY;
    }
}

table! {
    /// One rule of a `write` list: the writes it permits; each key left out matches any.
    ["write"] RuleTable RULE_KEYS {
        /// The master's unit ids, 0 to 255, and ranges "A-B"
        units: RuleUnits = RuleUnits::default(), Range(0, 255, None);
        /// Function codes that write (5, 6, 15, 16, 22, 23...)
        functions: Functions = Functions::default(), Range(1, 127, Some("a function code, 1 to 127"));
        /// The first and last address, "A-B", or one address
        addresses: Addresses = Addresses((0, 65535)), Range(0, 65535, None);
    }
}

table! {
    /// A TCP line's `tls` table: the gateway as a TLS client of the device
    /// (docs/security.md "A device behind TLS").
    ["line.tcp.tls"] TlsDeviceTable DEVICE_TLS_KEYS {
        /// The gateway's client certificate chain (PEM), presented to the device; required
        cert: String = String::new(), NonEmpty("the gateway's client certificate, PEM");
        /// Its private key (PEM); required
        key: String = String::new(), NonEmpty("the gateway's private key, PEM");
        /// The CA certificates (PEM) the device's certificate must chain to; required
        device_ca: String = String::new(), NonEmpty("the CA the device's certificate chains to, PEM");
        /// The name the device's certificate must carry; none: the host of address
        server_name: String = String::new(), NonEmpty("the name in the device's certificate");
    }
}

/// Who may connect to a listener and what they may do (docs/security.md).
#[derive(Debug, Clone, PartialEq, Default)]
pub(crate) struct ListenAccess {
    /// The source addresses taken; `None`: everyone.
    pub(crate) allow: Option<AllowList>,
    /// What every master of this listener may do.
    pub(crate) policy: Policy,
    /// Modbus/TCP Security: TLS with client certificates and roles.
    pub(crate) tls: Option<TlsListen>,
}

impl ListenAccess {
    /// Nothing set: everyone, every request, no TLS (a listener as before).
    pub(crate) fn is_open(&self) -> bool {
        self.allow.is_none() && self.policy.is_open() && self.tls.is_none()
    }
}

/// A listener's `tls` table.
#[derive(Debug, Clone, PartialEq)]
pub struct TlsListen {
    /// The gateway's certificate chain (PEM), leaf first.
    pub(crate) cert: PathBuf,
    /// Its private key (PEM: PKCS#8, PKCS#1 or SEC1).
    pub(crate) key: PathBuf,
    /// The CA certificates (PEM) a master's certificate must chain to.
    pub(crate) client_ca: PathBuf,
    /// The role of a certificate that carries none; `None`: such a master is refused.
    pub(crate) default_role: Option<String>,
    /// The most a TLS handshake may take, from the accept.
    pub(crate) handshake_timeout_ms: u64,
}

/// One `[[role]]`: a name a client certificate carries, and its policy.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct AccessRole {
    /// As in the certificate's Modbus role extension, compared exactly.
    pub(crate) name: String,
    /// What a master with this role may do.
    pub(crate) policy: Policy,
    /// Its masters' priority class on the lines (docs/masters.md "Priority"), over
    /// the listener's; `None`: the listener's.
    pub(crate) priority: Option<u8>,
}

/// A TCP line's `tls` table: the gateway as a TLS client of the device.
#[derive(Debug, Clone, PartialEq)]
pub struct TlsDevice {
    /// The gateway's client certificate chain (PEM), presented to the device.
    pub(crate) cert: PathBuf,
    /// Its private key (PEM).
    pub(crate) key: PathBuf,
    /// The CA certificates (PEM) the device's certificate must chain to.
    pub(crate) device_ca: PathBuf,
    /// The name the device's certificate must carry; `None`: the host of `address`.
    pub(crate) server_name: Option<String>,
}

/// `"A-B"` with A <= B <= `max`.
fn range(s: &str, max: u16) -> Result<(u16, u16), ValueError> {
    let bad = || format!("expected a number or a range like \"10-20\" (0 to {max}), got {s:?}");
    let (a, b) = s.split_once('-').ok_or_else(bad)?;
    let n = |x: &str| x.trim().parse::<u16>().ok().filter(|v| *v <= max);
    match (n(a), n(b)) {
        (Some(a), Some(b)) if a <= b => Ok((a, b)),
        (Some(_), Some(_)) => Err(format!("the range {s:?} is empty").into()),
        _ => Err(bad().into()),
    }
}

/// The largest number `check` takes.
fn most(check: &Check) -> i128 {
    match *check {
        Check::Range(_, max, _) => max,
        _ => i128::MAX,
    }
}

/// The items of an array, or what to say when `raw` is none; `empty`: what to say
/// when it has no item.
fn items<'r>(raw: &'r Raw, expected: &str, empty: &str) -> Result<&'r [Raw], ValueError> {
    match raw {
        Raw::List(items) if items.is_empty() => Err(empty.into()),
        Raw::List(items) => Ok(items),
        _ => Err(expected.into()),
    }
}

/// `allow = ["10.0.0.0/24", "::1"]`: at least one address or block, none twice.
impl Setting for Option<AllowList> {
    const KIND: ValueKind = ValueKind::List;
    fn read(raw: &Raw, _check: &Check) -> Result<Self, ValueError> {
        let expected =
            "expected an array of addresses and CIDR blocks, like [\"10.0.0.0/24\", \"::1\"]";
        let empty = "must list at least one address (leave allow out to take everyone)";
        let mut nets = Vec::new();
        for (i, item) in items(raw, expected, empty)?.iter().enumerate() {
            let net = String::read(item, &Any)
                .and_then(|s| s.parse::<Net>().map_err(|e| ValueError::new(e.to_string())))
                .map_err(|e| e.item(i))?;
            if nets.contains(&net) {
                return Err(ValueError::new(format!("{net} is listed twice")).item(i));
            }
            nets.push(net);
        }
        Ok(Some(AllowList::new(nets)))
    }
    fn print(&self) -> String {
        let nets = self.iter().flat_map(|a| a.nets().iter());
        let nets: Vec<String> = nets.map(|n| format!("\"{n}\"")).collect();
        format!("[{}]", nets.join(", "))
    }
}

/// `write = [{ units = [1], functions = [6, 16], addresses = "100-199" }, ...]`: at
/// least one rule, none empty.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct WriteRules(pub(crate) Vec<WriteRule>);

impl Setting for WriteRules {
    const KIND: ValueKind = ValueKind::List;
    fn read(raw: &Raw, _check: &Check) -> Result<Self, ValueError> {
        let expected = "expected an array of rules, like [{ units = [1], functions = [6], addresses = \"0-99\" }]";
        let empty = "must list at least one rule (write = [] would be read_only = true)";
        let mut rules = Vec::new();
        for (i, item) in items(raw, expected, empty)?.iter().enumerate() {
            rules.push(rule(item).map_err(|e| e.item(i))?);
        }
        Ok(Self(rules))
    }
    fn print(&self) -> String {
        let rules: Vec<String> = self.0.iter().map(WriteRule::to_string).collect();
        format!("[{}]", rules.join(", "))
    }
}

/// One `write` rule, read by [`RULE_KEYS`].
fn rule(raw: &Raw) -> Result<WriteRule, ValueError> {
    let not_table = "expected a rule: a table of units, functions, addresses";
    let (t, given) = read_table(raw, RULE_KEYS, not_table)?;
    let r = WriteRule {
        units: given.contains(&"units").then_some(t.units.0),
        functions: given.contains(&"functions").then_some(t.functions.0),
        addresses: given.contains(&"addresses").then_some(t.addresses.0),
    };
    if r == WriteRule::default() {
        return Err("an empty rule permits every write: name units, functions or addresses (or leave write out)".into());
    }
    Ok(r)
}

/// A rule's `units = [0, 1, "10-20"]`: unit ids as the master sends them.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct RuleUnits(pub(crate) UnitSet);

impl Setting for RuleUnits {
    const KIND: ValueKind = ValueKind::List;
    fn read(raw: &Raw, check: &Check) -> Result<Self, ValueError> {
        let expected = "expected an array of unit ids and ranges like \"10-20\"";
        let empty = "must list at least one unit id (leave units out for every unit)";
        let mut set = UnitSet::default();
        for (i, id) in items(raw, expected, empty)?.iter().enumerate() {
            let (a, b) = match id {
                Raw::Str(s) => range(s, most(check) as u16),
                _ => u8::read(id, check).map(|u| (u16::from(u), u16::from(u))),
            }
            .map_err(|e| e.item(i))?;
            for u in a..=b {
                set.insert(u as u8);
            }
        }
        Ok(Self(set))
    }
    fn print(&self) -> String {
        self.0.to_string()
    }
}

/// A rule's `functions = [5, 6, 0x10]`: codes that may act on the device, none twice.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Functions(pub(crate) Vec<u8>);

impl Setting for Functions {
    const KIND: ValueKind = ValueKind::List;
    fn read(raw: &Raw, check: &Check) -> Result<Self, ValueError> {
        let expected = "expected an array of function codes, like [6, 16]";
        let empty = "must list at least one function code (leave functions out for every write)";
        let mut out = Vec::new();
        for (i, c) in items(raw, expected, empty)?.iter().enumerate() {
            let fc = u8::read(c, check).map_err(|e| e.item(i))?;
            if FunctionCode::new(fc).is_read() {
                let m = format!("function {fc} only reads, and reads are always permitted: a write rule lists codes that write (5, 6, 15, 16, 22, 23, ...)");
                return Err(ValueError::new(m).item(i));
            }
            if out.contains(&fc) {
                return Err(ValueError::new(format!("function {fc} is listed twice")).item(i));
            }
            out.push(fc);
        }
        Ok(Self(out))
    }
    fn print(&self) -> String {
        let fcs: Vec<String> = self.0.iter().map(u8::to_string).collect();
        format!("[{}]", fcs.join(", "))
    }
}

/// A rule's `addresses = "100-199"`, or one address `addresses = 100`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Addresses(pub(crate) (u16, u16));

impl Setting for Addresses {
    const KIND: ValueKind = ValueKind::Str;
    fn read(raw: &Raw, check: &Check) -> Result<Self, ValueError> {
        match raw {
            Raw::Str(s) => range(s, most(check) as u16).map(Self),
            _ => u32::read(raw, check).map(|a| Self((a as u16, a as u16))),
        }
    }
    fn print(&self) -> String {
        format!("\"{}-{}\"", self.0 .0, self.0 .1)
    }
}

/// A listener's `tls` table, read by [`LISTEN_TLS_KEYS`]: `cert`, `key` and
/// `client_ca` required.
impl Setting for Option<TlsListen> {
    const KIND: ValueKind = ValueKind::List;
    fn read(raw: &Raw, _check: &Check) -> Result<Self, ValueError> {
        let not_table = "expected a table: { cert = ..., key = ..., client_ca = ... }";
        let (t, given) = read_table(raw, LISTEN_TLS_KEYS, not_table)?;
        let missing = |key: &str, why: &str| ValueError::new(format!("missing: {why}")).value(key);
        for (key, why) in [
            ("cert", "the gateway's certificate (PEM)"),
            ("key", "the gateway's private key (PEM)"),
            ("client_ca", "the CA masters' certificates must chain to (PEM); Modbus/TCP Security requires client certificates"),
        ] {
            if !given.contains(&key) {
                return Err(missing(key, why));
            }
        }
        Ok(Some(TlsListen {
            cert: t.cert.into(),
            key: t.key.into(),
            client_ca: t.client_ca.into(),
            default_role: given.contains(&"default_role").then_some(t.default_role),
            handshake_timeout_ms: t.handshake_timeout_ms,
        }))
    }
    fn print(&self) -> String {
        let Some(t) = self else {
            return "{}".into();
        };
        let mut parts = vec![
            format!("cert = {}", quoted(&t.cert)),
            format!("key = {}", quoted(&t.key)),
            format!("client_ca = {}", quoted(&t.client_ca)),
        ];
        if let Some(r) = &t.default_role {
            parts.push(format!("default_role = {}", r.print()));
        }
        parts.push(format!("handshake_timeout_ms = {}", t.handshake_timeout_ms));
        format!("{{ {} }}", parts.join(", "))
    }
}

/// A path as the file writes it.
pub(super) fn quoted(p: &std::path::Path) -> String {
    p.display().to_string().print()
}

/// `read_only` and `write` of a listener or a role: both at once is refused, at
/// `read_only`; `path` is what messages call the table.
pub(super) fn policy(read_only: bool, write: WriteRules, path: &str) -> Result<Policy, ValueError> {
    if read_only && !write.0.is_empty() {
        let m = format!(
            "read_only = true refuses every write: give {path}.read_only or {path}.write, not both"
        );
        return Err(ValueError::new(m).value("read_only"));
    }
    Ok(Policy {
        read_only,
        write: write.0,
    })
}

/// A `[[listen]]`'s own keys ([`LISTEN_KEYS`]) from `raw`, a table of them alone;
/// `path` is what messages call it (`listen[0]`).
pub(super) fn listen(raw: &Raw, path: &str) -> Result<ListenKeys, ValueError> {
    let (t, _) = read_table(raw, LISTEN_KEYS, "expected a table ([[listen]])")?;
    let policy = policy(t.read_only, t.write, path)?;
    if t.transport == Transport::Udp {
        // A datagram is one whole request: RTU's CRC and TLS's stream have no place.
        if t.framing != ListenFraming::Mbap {
            let m = "transport = \"udp\" carries one MBAP request a datagram: framing must be mbap";
            return Err(ValueError::new(m).value("framing"));
        }
        if t.tls.is_some() {
            let m = "transport = \"udp\" has no TLS (Modbus/TCP Security is over TCP): remove tls or the transport";
            return Err(ValueError::new(m).value("tls"));
        }
    } else if t.notifications {
        // A TCP master's connection is its own: it gets the notifications whenever
        // its line broadcasts them.
        let m = "notifications is a UDP listener's (transport = \"udp\"): a TCP master gets a line's notifications whenever the line broadcasts them (notifications = \"broadcast\" in its relay table)";
        return Err(ValueError::new(m).value("notifications"));
    }
    let access = ListenAccess {
        allow: t.allow,
        policy,
        tls: t.tls,
    };
    Ok(ListenKeys {
        access,
        framing: t.framing,
        priority: t.priority,
        transport: t.transport,
        notifications: t.notifications,
    })
}

/// A `[[listen]]`'s own keys, read.
pub(super) struct ListenKeys {
    pub(super) access: ListenAccess,
    pub(super) framing: ListenFraming,
    pub(super) priority: u8,
    pub(super) transport: Transport,
    pub(super) notifications: bool,
}

/// The keys of [`LISTEN_KEYS`] that say who may connect and what they may do: those
/// in `[tcp]` are refused, saying they belong in a `[[listen]]`.
pub(super) fn is_access_key(name: &str) -> bool {
    LISTEN_KEYS.iter().any(|k| {
        k.name == name && !["framing", "priority", "transport", "notifications"].contains(&k.name)
    })
}

/// Each listener's `tls.default_role` names a `[[role]]`: the index of the first that
/// does not, and why.
pub(super) fn default_roles(
    listeners: &[super::ListenConfig],
    roles: &[AccessRole],
) -> Result<(), (usize, String)> {
    for (i, l) in listeners.iter().enumerate() {
        let Some(role) = l.access.tls.as_ref().and_then(|t| t.default_role.as_ref()) else {
            continue;
        };
        if !roles.iter().any(|r| &r.name == role) {
            let names: Vec<&str> = roles.iter().map(|r| r.name.as_str()).collect();
            let m = if names.is_empty() {
                format!("no [[role]] is named {role:?} (there are no [[role]] tables)")
            } else {
                format!(
                    "no [[role]] is named {role:?}; the roles are {}",
                    names.join(", ")
                )
            };
            return Err((i, m));
        }
    }
    Ok(())
}

/// The `[[role]]` tables, read by [`ROLE_KEYS`]: each with a unique, non-empty name;
/// `path` is what messages call them (`role`).
pub(super) fn roles(raw: &Raw, path: &str) -> Result<Vec<AccessRole>, ValueError> {
    let Raw::List(tables) = raw else {
        return Err("expected [[role]] tables".into());
    };
    let mut out: Vec<AccessRole> = Vec::new();
    for (i, t) in tables.iter().enumerate() {
        let here = format!("{path}[{i}]");
        let role = || -> Result<AccessRole, ValueError> {
            let (t, given) = read_table(t, ROLE_KEYS, "expected a table ([[role]])")?;
            if !given.contains(&"name") {
                let m = "missing: the role's name, as client certificates carry it";
                return Err(ValueError::new(m).value("name"));
            }
            if let Some(j) = out.iter().position(|r| r.name == t.name) {
                let m = format!("role {:?} is also {path}[{j}]", t.name);
                return Err(ValueError::new(m).value("name"));
            }
            Ok(AccessRole {
                policy: policy(t.read_only, t.write, &here)?,
                priority: given.contains(&"priority").then_some(t.priority),
                name: t.name,
            })
        };
        let role = role().map_err(|e| e.item(i))?;
        out.push(role);
    }
    Ok(out)
}

/// A TCP line's `tls` table ([`tls_device`]).
impl Setting for Option<TlsDevice> {
    const KIND: ValueKind = ValueKind::List;
    fn read(raw: &Raw, _check: &Check) -> Result<Self, ValueError> {
        tls_device(raw).map(Some)
    }
    fn print(&self) -> String {
        let Some(t) = self else {
            return "{}".into();
        };
        format!("{{ {} }}", client_parts(t, "device_ca").join(", "))
    }
}

/// The keys of mbgate's side of a TLS client table as the file writes them, the CA
/// under `ca` (a TCP line's `device_ca`, a dial's `server_ca`).
pub(super) fn client_parts(t: &TlsDevice, ca: &str) -> Vec<String> {
    let mut parts = vec![
        format!("cert = {}", quoted(&t.cert)),
        format!("key = {}", quoted(&t.key)),
        format!("{ca} = {}", quoted(&t.device_ca)),
    ];
    if let Some(n) = &t.server_name {
        parts.push(format!("server_name = {}", n.print()));
    }
    parts
}

/// A TCP line's `tls` table, read by [`DEVICE_TLS_KEYS`]: `cert`, `key` and
/// `device_ca` required, `server_name` a DNS name or an address.
fn tls_device(raw: &Raw) -> Result<TlsDevice, ValueError> {
    let not_table = "expected a table: { cert = ..., key = ..., device_ca = ... }";
    let (t, given) = read_table(raw, DEVICE_TLS_KEYS, not_table)?;
    let ca = (
        "device_ca",
        "the CA the device's certificate must chain to (PEM)",
    );
    let files = (t.cert, t.key, t.device_ca);
    tls_client(&given, "device", ca, files, t.server_name)
}

/// mbgate's side of a TLS client table (a TCP line's, a dial's): `cert`, `key` and
/// the CA (`ca`: its key and what it is) required, `server_name` a DNS name or an
/// address; `peer` is what the far end is called.
pub(super) fn tls_client(
    given: &[&str],
    peer: &str,
    ca: (&str, &str),
    (cert, key, ca_file): (String, String, String),
    server_name: String,
) -> Result<TlsDevice, ValueError> {
    let cert_why = format!("the gateway's client certificate (PEM), presented to the {peer}");
    for (k, why) in [
        ("cert", cert_why.as_str()),
        ("key", "the gateway's private key (PEM)"),
        ca,
    ] {
        if !given.contains(&k) {
            return Err(ValueError::new(format!("missing: {why}")).value(k));
        }
    }
    let server_name = given.contains(&"server_name").then_some(server_name);
    if let Some(s) = &server_name {
        if rustls::pki_types::ServerName::try_from(s.as_str()).is_err() {
            let m = format!("{s:?} is not a DNS name or an IP address");
            return Err(ValueError::new(m).value("server_name"));
        }
    }
    Ok(TlsDevice {
        cert: cert.into(),
        key: key.into(),
        device_ca: ca_file.into(),
        server_name,
    })
}

mod print;
pub(crate) use print::{device_to_toml, effective, listen_to_toml, roles_to_toml};

#[cfg(test)]
mod tests;
