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

use super::raw::{bad, entries, raw_value, suggest, Bad};
use super::{Check, Setting};
use crate::access::{AllowList, Net, Policy, UnitSet, WriteRule};
use crate::frame::function::FunctionCode;
use std::path::PathBuf;
use toml::de::{DeTable, DeValue};
use toml::Spanned;

/// The keys a `[[listen]]` has beyond those of `[tcp]` and `framing`.
pub(super) const LISTEN_ACCESS: [&str; 4] = ["allow", "read_only", "write", "tls"];
/// The keys of a listener's `tls` table.
const LISTEN_TLS: [&str; 5] = [
    "cert",
    "key",
    "client_ca",
    "default_role",
    "handshake_timeout_ms",
];
/// The keys of a `[[role]]`.
const ROLE: [&str; 4] = ["name", "read_only", "write", "priority"];
/// The keys of a `write` rule.
const RULE: [&str; 3] = ["units", "functions", "addresses"];
/// The keys of a TCP line's `tls` table.
const LINE_TLS: [&str; 4] = ["cert", "key", "device_ca", "server_name"];

/// The default `handshake_timeout_ms`.
pub(crate) const HANDSHAKE_TIMEOUT_MS: u64 = 10_000;

/// Who may connect to a listener and what they may do (docs/security.md).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ListenAccess {
    /// The source addresses taken; `None`: everyone.
    pub allow: Option<AllowList>,
    /// What every master of this listener may do.
    pub policy: Policy,
    /// Modbus/TCP Security: TLS with client certificates and roles.
    pub tls: Option<TlsListen>,
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
    pub cert: PathBuf,
    /// Its private key (PEM: PKCS#8, PKCS#1 or SEC1).
    pub key: PathBuf,
    /// The CA certificates (PEM) a master's certificate must chain to.
    pub client_ca: PathBuf,
    /// The role of a certificate that carries none; `None`: such a master is refused.
    pub default_role: Option<String>,
    /// The most a TLS handshake may take, from the accept.
    pub handshake_timeout_ms: u64,
}

/// One `[[role]]`: a name a client certificate carries, and its policy.
#[derive(Debug, Clone, PartialEq)]
pub struct Role {
    /// As in the certificate's Modbus role extension, compared exactly.
    pub name: String,
    /// What a master with this role may do.
    pub policy: Policy,
    /// Its masters' priority class on the lines (docs/masters.md "Priority"), over
    /// the listener's; `None`: the listener's.
    pub priority: Option<u8>,
}

/// A TCP line's `tls` table: the gateway as a TLS client of the device.
#[derive(Debug, Clone, PartialEq)]
pub struct TlsDevice {
    /// The gateway's client certificate chain (PEM), presented to the device.
    pub cert: PathBuf,
    /// Its private key (PEM).
    pub key: PathBuf,
    /// The CA certificates (PEM) the device's certificate must chain to.
    pub device_ca: PathBuf,
    /// The name the device's certificate must carry; `None`: the host of `address`.
    pub server_name: Option<String>,
}

/// A value as the checks see it.
fn raw(v: &Spanned<DeValue>) -> super::Raw {
    raw_value(v.get_ref())
}

fn unknown<T>(k: &Spanned<std::borrow::Cow<str>>, key: &str, expected: &[&str]) -> Result<T, Bad> {
    let mut m = format!("unknown key; expected one of {}", expected.join(", "));
    if let Some(s) = suggest(k.get_ref(), expected) {
        m += &format!(" (did you mean `{s}`?)");
    }
    bad(k.span().start, key, m)
}

/// `allow = ["10.0.0.0/24", "::1"]`: at least one address or block.
pub(super) fn allow(v: &Spanned<DeValue>, key: &str) -> Result<AllowList, Bad> {
    let DeValue::Array(items) = v.get_ref() else {
        return bad(
            v.span().start,
            key,
            "expected an array of addresses and CIDR blocks, like [\"10.0.0.0/24\", \"::1\"]",
        );
    };
    if items.is_empty() {
        return bad(
            v.span().start,
            key,
            "must list at least one address (leave allow out to take everyone)",
        );
    }
    let mut nets = Vec::new();
    for item in items.iter() {
        let at = item.span().start;
        let s = String::read(&raw(item), &Check::Any).or_else(|m| bad(at, key, m))?;
        let net: Net = s.parse().or_else(|m| bad(at, key, m))?;
        if nets.contains(&net) {
            return bad(at, key, format!("{net} is listed twice"));
        }
        nets.push(net);
    }
    Ok(AllowList::new(nets))
}

/// The most priority classes there are: `priority` is 0 (the default, the lowest) to
/// this.
pub(crate) const PRIORITY_MAX: u8 = 7;

/// `priority = N` of a listener or a role: a class from 0 to [`PRIORITY_MAX`].
pub(super) fn priority(v: &Spanned<DeValue>, key: &str) -> Result<u8, Bad> {
    let said = "0 (the default, the lowest) to 7";
    u8::read(
        &raw(v),
        &Check::Range(0, i128::from(PRIORITY_MAX), Some(said)),
    )
    .or_else(|m| bad(v.span().start, key, m))
}

/// `read_only` and `write` of a listener or a role: `table` is where they are, `path`
/// what messages call it.
pub(super) fn policy(table: &DeTable, path: &str) -> Result<Policy, Bad> {
    let mut p = Policy::default();
    let mut read_only_at = None;
    if let Some(v) = table.get("read_only") {
        let key = format!("{path}.read_only");
        p.read_only = bool::read(&raw(v), &Check::Any).or_else(|m| bad(v.span().start, &key, m))?;
        read_only_at = Some(v.span().start);
    }
    if let Some(v) = table.get("write") {
        let key = format!("{path}.write");
        p.write = write_rules(v, &key)?;
        if p.read_only {
            let m = format!(
                "read_only = true refuses every write: give {path}.read_only or {path}.write, not both"
            );
            return bad(
                read_only_at.unwrap_or(v.span().start),
                &format!("{path}.read_only"),
                m,
            );
        }
    }
    Ok(p)
}

/// `write = [{ units = [1], functions = [6, 16], addresses = "100-199" }, ...]`.
fn write_rules(v: &Spanned<DeValue>, key: &str) -> Result<Vec<WriteRule>, Bad> {
    let DeValue::Array(items) = v.get_ref() else {
        return bad(v.span().start, key, "expected an array of rules, like [{ units = [1], functions = [6], addresses = \"0-99\" }]");
    };
    if items.is_empty() {
        return bad(
            v.span().start,
            key,
            "must list at least one rule (write = [] would be read_only = true)",
        );
    }
    let mut rules = Vec::new();
    for (i, item) in items.iter().enumerate() {
        let here = format!("{key}[{i}]");
        let DeValue::Table(t) = item.get_ref() else {
            return bad(
                item.span().start,
                &here,
                "expected a rule: a table of units, functions, addresses",
            );
        };
        let mut r = WriteRule::default();
        for (k, v) in entries(t) {
            let full = format!("{here}.{}", k.get_ref());
            match k.get_ref().as_ref() {
                "units" => r.units = Some(units(v, &full)?),
                "functions" => r.functions = Some(functions(v, &full)?),
                "addresses" => r.addresses = Some(addresses(v, &full)?),
                _ => return unknown(k, &full, &RULE),
            }
        }
        if r == WriteRule::default() {
            let m = "an empty rule permits every write: name units, functions or addresses (or leave write out)";
            return bad(item.span().start, &here, m);
        }
        rules.push(r);
    }
    Ok(rules)
}

/// `units = [0, 1, "10-20"]`: unit ids 0 to 255 as the master sends them.
fn units(v: &Spanned<DeValue>, key: &str) -> Result<UnitSet, Bad> {
    let DeValue::Array(ids) = v.get_ref() else {
        return bad(
            v.span().start,
            key,
            "expected an array of unit ids and ranges like \"10-20\"",
        );
    };
    if ids.is_empty() {
        return bad(
            v.span().start,
            key,
            "must list at least one unit id (leave units out for every unit)",
        );
    }
    let mut set = UnitSet::default();
    for id in ids.iter() {
        let at = id.span().start;
        let (a, b) = match id.get_ref() {
            DeValue::String(s) => range(s, 255).or_else(|m| bad(at, key, m))?,
            _ => {
                let u =
                    u8::read(&raw(id), &Check::Range(0, 255, None)).or_else(|m| bad(at, key, m))?;
                (u16::from(u), u16::from(u))
            }
        };
        for u in a..=b {
            set.insert(u as u8);
        }
    }
    Ok(set)
}

/// `functions = [5, 6, 0x10]`: codes that may act on the device.
fn functions(v: &Spanned<DeValue>, key: &str) -> Result<Vec<u8>, Bad> {
    let DeValue::Array(codes) = v.get_ref() else {
        return bad(
            v.span().start,
            key,
            "expected an array of function codes, like [6, 16]",
        );
    };
    if codes.is_empty() {
        return bad(
            v.span().start,
            key,
            "must list at least one function code (leave functions out for every write)",
        );
    }
    let mut out = Vec::new();
    for c in codes.iter() {
        let at = c.span().start;
        let fc = u8::read(
            &raw(c),
            &Check::Range(1, 127, Some("a function code, 1 to 127")),
        )
        .or_else(|m| bad(at, key, m))?;
        if FunctionCode::new(fc).is_read() {
            let m = format!("function {fc} only reads, and reads are always permitted: a write rule lists codes that write (5, 6, 15, 16, 22, 23, ...)");
            return bad(at, key, m);
        }
        if out.contains(&fc) {
            return bad(at, key, format!("function {fc} is listed twice"));
        }
        out.push(fc);
    }
    Ok(out)
}

/// `addresses = "100-199"` or one address `addresses = 100`.
fn addresses(v: &Spanned<DeValue>, key: &str) -> Result<(u16, u16), Bad> {
    let at = v.span().start;
    match v.get_ref() {
        DeValue::String(s) => {
            let (a, b) = range(s, 65535).or_else(|m| bad(at, key, m))?;
            Ok((a, b))
        }
        _ => {
            let a =
                u32::read(&raw(v), &Check::Range(0, 65535, None)).or_else(|m| bad(at, key, m))?;
            Ok((a as u16, a as u16))
        }
    }
}

/// `"A-B"` with A <= B <= `max`.
fn range(s: &str, max: u16) -> Result<(u16, u16), String> {
    let bad = || format!("expected a number or a range like \"10-20\" (0 to {max}), got {s:?}");
    let (a, b) = s.split_once('-').ok_or_else(bad)?;
    let n = |x: &str| x.trim().parse::<u16>().ok().filter(|v| *v <= max);
    match (n(a), n(b)) {
        (Some(a), Some(b)) if a <= b => Ok((a, b)),
        (Some(_), Some(_)) => Err(format!("the range {s:?} is empty")),
        _ => Err(bad()),
    }
}

/// A `[[listen]]`'s security keys, from its `table`; `path` is `listen[0]`. Also where
/// its `default_role` is, for [`default_roles`].
pub(super) fn listen(table: &DeTable, path: &str) -> Result<(ListenAccess, Option<usize>), Bad> {
    let allow = match table.get("allow") {
        Some(a) => Some(allow(a, &format!("{path}.allow"))?),
        None => None,
    };
    let (mut tls, mut role_at) = (None, None);
    if let Some(t) = table.get("tls") {
        tls = Some(tls_listen(t, &format!("{path}.tls"))?);
        if let DeValue::Table(t) = t.get_ref() {
            role_at = t.get("default_role").map(|r| r.span().start);
        }
    }
    let policy = policy(table, path)?;
    Ok((ListenAccess { allow, policy, tls }, role_at))
}

/// `[tcp]` is the one listener open to all: the security keys belong in a
/// `[[listen]]` table, and the message says so rather than "unknown key".
pub(super) fn not_in_tcp(v: &Spanned<DeValue>) -> Result<(), Bad> {
    if let DeValue::Table(t) = v.get_ref() {
        for (k, _) in entries(t) {
            let name = k.get_ref().as_ref();
            if LISTEN_ACCESS.contains(&name) {
                let m = format!(
                    "{name} belongs in a [[listen]] table (write [[listen]] with address = \
                     the listen address instead of [tcp]; docs/security.md)"
                );
                return bad(k.span().start, &format!("tcp.{name}"), m);
            }
        }
    }
    Ok(())
}

/// Each listener's `tls.default_role` names a `[[role]]`; `listeners` with where each
/// one's `default_role` is.
pub(super) fn default_roles(
    listeners: &[(usize, super::ListenConfig)],
    roles: &[(usize, Role)],
) -> Result<(), Bad> {
    for (i, (at, l)) in listeners.iter().enumerate() {
        let Some(role) = l.access.tls.as_ref().and_then(|t| t.default_role.as_ref()) else {
            continue;
        };
        if !roles.iter().any(|(_, r)| &r.name == role) {
            let names: Vec<&str> = roles.iter().map(|(_, r)| r.name.as_str()).collect();
            let m = if names.is_empty() {
                format!("no [[role]] is named {role:?} (there are no [[role]] tables)")
            } else {
                format!(
                    "no [[role]] is named {role:?}; the roles are {}",
                    names.join(", ")
                )
            };
            return bad(*at, &format!("listen[{i}].tls.default_role"), m);
        }
    }
    Ok(())
}

/// A path: a non-empty string.
fn path(v: &Spanned<DeValue>, key: &str, what: &'static str) -> Result<PathBuf, Bad> {
    let s =
        String::read(&raw(v), &Check::NonEmpty(what)).or_else(|m| bad(v.span().start, key, m))?;
    Ok(PathBuf::from(s))
}

/// A listener's `tls = { cert, key, client_ca, default_role, handshake_timeout_ms }`.
pub(super) fn tls_listen(v: &Spanned<DeValue>, key: &str) -> Result<TlsListen, Bad> {
    let DeValue::Table(t) = v.get_ref() else {
        return bad(
            v.span().start,
            key,
            "expected a table: { cert = ..., key = ..., client_ca = ... }",
        );
    };
    let (mut cert, mut pkey, mut ca) = (None, None, None);
    let mut tls = TlsListen {
        cert: PathBuf::new(),
        key: PathBuf::new(),
        client_ca: PathBuf::new(),
        default_role: None,
        handshake_timeout_ms: HANDSHAKE_TIMEOUT_MS,
    };
    for (k, item) in entries(t) {
        let full = format!("{key}.{}", k.get_ref());
        let at = item.span().start;
        match k.get_ref().as_ref() {
            "cert" => cert = Some(path(item, &full, "the gateway's certificate, PEM")?),
            "key" => pkey = Some(path(item, &full, "the gateway's private key, PEM")?),
            "client_ca" => {
                ca = Some(path(
                    item,
                    &full,
                    "the CA certificates masters' certificates chain to, PEM",
                )?)
            }
            "default_role" => {
                let r = String::read(&raw(item), &Check::NonEmpty("a [[role]] name"))
                    .or_else(|m| bad(at, &full, m))?;
                tls.default_role = Some(r);
            }
            "handshake_timeout_ms" => {
                tls.handshake_timeout_ms = u64::read(&raw(item), &Check::Range(100, 600_000, None))
                    .or_else(|m| bad(at, &full, m))?;
            }
            _ => return unknown(k, &full, &LISTEN_TLS),
        }
    }
    let missing = |what: &str, why: &str| {
        bad(
            v.span().start,
            &format!("{key}.{what}"),
            format!("missing: {why}"),
        )
    };
    tls.cert = match cert {
        Some(c) => c,
        None => return missing("cert", "the gateway's certificate (PEM)"),
    };
    tls.key = match pkey {
        Some(k) => k,
        None => return missing("key", "the gateway's private key (PEM)"),
    };
    tls.client_ca = match ca {
        Some(c) => c,
        None => return missing("client_ca", "the CA masters' certificates must chain to (PEM); Modbus/TCP Security requires client certificates"),
    };
    Ok(tls)
}

/// The `[[role]]` tables: each with a unique, non-empty name.
pub(super) fn roles(v: &Spanned<DeValue>, path: &str) -> Result<Vec<(usize, Role)>, Bad> {
    let DeValue::Array(tables) = v.get_ref() else {
        return bad(v.span().start, path, "expected [[role]] tables");
    };
    let mut out: Vec<(usize, Role)> = Vec::new();
    for (i, t) in tables.iter().enumerate() {
        let here = format!("{path}[{i}]");
        let DeValue::Table(table) = t.get_ref() else {
            return bad(t.span().start, &here, "expected a table ([[role]])");
        };
        for (k, _) in entries(table) {
            if !ROLE.contains(&k.get_ref().as_ref()) {
                return unknown(k, &format!("{here}.{}", k.get_ref()), &ROLE);
            }
        }
        let Some(n) = table.get("name") else {
            return bad(
                t.span().start,
                &format!("{here}.name"),
                "missing: the role's name, as client certificates carry it",
            );
        };
        let key = format!("{here}.name");
        let name = String::read(&raw(n), &Check::NonEmpty("the role's name"))
            .or_else(|m| bad(n.span().start, &key, m))?;
        if let Some(j) = out.iter().position(|(_, r)| r.name == name) {
            return bad(
                n.span().start,
                &key,
                format!("role {name:?} is also {path}[{j}]"),
            );
        }
        let policy = policy(table, &here)?;
        let priority = match table.get("priority") {
            Some(v) => Some(priority(v, &format!("{here}.priority"))?),
            None => None,
        };
        let role = Role {
            name,
            policy,
            priority,
        };
        out.push((t.span().start, role));
    }
    Ok(out)
}

/// A TCP line's `tls = { cert, key, device_ca, server_name }`.
pub(super) fn tls_device(v: &Spanned<DeValue>, key: &str) -> Result<TlsDevice, Bad> {
    let DeValue::Table(t) = v.get_ref() else {
        return bad(
            v.span().start,
            key,
            "expected a table: { cert = ..., key = ..., device_ca = ... }",
        );
    };
    let (mut cert, mut pkey, mut ca, mut name) = (None, None, None, None);
    for (k, item) in entries(t) {
        let full = format!("{key}.{}", k.get_ref());
        match k.get_ref().as_ref() {
            "cert" => cert = Some(path(item, &full, "the gateway's client certificate, PEM")?),
            "key" => pkey = Some(path(item, &full, "the gateway's private key, PEM")?),
            "device_ca" => {
                ca = Some(path(
                    item,
                    &full,
                    "the CA the device's certificate chains to, PEM",
                )?)
            }
            "server_name" => {
                let s = String::read(
                    &raw(item),
                    &Check::NonEmpty("the name in the device's certificate"),
                )
                .or_else(|m| bad(item.span().start, &full, m))?;
                if rustls::pki_types::ServerName::try_from(s.as_str()).is_err() {
                    return bad(
                        item.span().start,
                        &full,
                        format!("{s:?} is not a DNS name or an IP address"),
                    );
                }
                name = Some(s);
            }
            _ => return unknown(k, &full, &LINE_TLS),
        }
    }
    let missing = |what: &str, why: &str| {
        bad(
            v.span().start,
            &format!("{key}.{what}"),
            format!("missing: {why}"),
        )
    };
    let Some(cert) = cert else {
        return missing(
            "cert",
            "the gateway's client certificate (PEM), presented to the device",
        );
    };
    let Some(key_path) = pkey else {
        return missing("key", "the gateway's private key (PEM)");
    };
    let Some(device_ca) = ca else {
        return missing(
            "device_ca",
            "the CA the device's certificate must chain to (PEM)",
        );
    };
    Ok(TlsDevice {
        cert,
        key: key_path,
        device_ca,
        server_name: name,
    })
}

mod print;
pub(crate) use print::{device_to_toml, effective, listen_to_toml, roles_to_toml};

#[cfg(test)]
mod tests;
