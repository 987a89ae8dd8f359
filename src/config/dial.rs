//! The `[[dial]]` tables (docs/dialing.md): masters mbgate connects out to instead of
//! waiting for them, each with its reconnect bounds, its identity and heartbeat bytes
//! and what its requests may do. Read, checked and printed here, so the rest of the
//! configuration code carries one field for them.
//!
//! ```toml
//! [[dial]]
//! address = "scada.example.net:502"
//! identity = "site-17"
//! heartbeat = "hex:ff fe 00 01"
//! heartbeat_ms = 30000
//! read_only = true
//! ```

use super::access::{policy, WriteRules, PRIORITY};
use super::raw::read_table;
use super::{table, Check, HostPort, Key, ListenConfig, ListenFraming, Raw, Setting, TcpConfig};
use super::{Any, NonEmpty, Range, ValueError, ValueKind};
use crate::access::Policy;
use std::net::SocketAddr;

table! {
    /// One `[[dial]]` as the file gives it (docs/configuration.md "Dialing a master").
    ["dial"] DialTable DIAL_KEYS {
        /// "HOST:PORT" of the master's server; the name is resolved again at each attempt; required
        address: HostPort = HostPort::default(), NonEmpty("host:port of the master's server");
        /// How the server frames its requests: mbap (Modbus/TCP) or rtu (RTU over TCP)
        framing: ListenFraming = ListenFraming::Mbap, Any;
        /// Every request that may act on a device is answered 0x01
        read_only: bool = false, Any;
        /// Rules { units, functions, addresses }: only the writes one of them matches pass
        write: WriteRules = WriteRules::default(), Any;
        /// Its requests' priority class on every line, 0 (the lowest) to 7
        priority: u8 = 0, PRIORITY;
        /// Bytes sent once the connection opens: text, or "hex:" and hex digits; none: nothing
        identity: Payload = Payload::default(), Any;
        /// Bytes sent when no request came for heartbeat_ms: text, or "hex:" and hex digits; none: nothing
        heartbeat: Payload = Payload::default(), Any;
        /// Quiet time before each heartbeat
        heartbeat_ms: u64 = 30_000, Range(100, 86_400_000, None);
        /// First wait before dialing again after a failure (then doubled, with jitter)
        backoff_min_ms: u64 = 1_000, Range(10, 3_600_000, None);
        /// Longest wait before dialing again
        backoff_max_ms: u64 = 60_000, Range(10, 3_600_000, None);
        /// The most a connect (and a TLS handshake) may take; an answer to the identity or a heartbeat is owed this long
        connect_timeout_ms: u64 = 10_000, Range(100, 600_000, None);
        /// Close the connection and dial again when no request came and no reply went out this long (heartbeats and their answers are none); 0: never
        idle_timeout_ms: u64 = 0, Range(0, u64::MAX as i128, Some("0 (never) or a number of milliseconds"));
        /// Modbus/TCP Security with mbgate as the client: { cert, key, server_ca, server_name, default_role }
        tls: Option<TlsDial> = None, Any;
    }
}

table! {
    /// A dial's `tls` table (docs/dialing.md "TLS").
    ["dial.tls"] TlsDialTable DIAL_TLS_KEYS {
        /// The gateway's client certificate chain (PEM), presented to the server; required
        cert: String = String::new(), NonEmpty("the gateway's client certificate, PEM");
        /// Its private key (PEM); required
        key: String = String::new(), NonEmpty("the gateway's private key, PEM");
        /// The CA certificates (PEM) the server's certificate must chain to; required
        server_ca: String = String::new(), NonEmpty("the CA the server's certificate chains to, PEM");
        /// The name the server's certificate must carry; none: the host of address
        server_name: String = String::new(), NonEmpty("the name in the server's certificate");
        /// The role of a server certificate that carries none; none: such a server is refused
        default_role: String = String::new(), NonEmpty("a [[role]] name");
    }
}

/// A dial's `tls` table: mbgate verifies the server, presents its own certificate,
/// and takes the role for the access rules from the server's certificate.
#[derive(Debug, Clone, PartialEq)]
pub struct TlsDial {
    /// The client side as a TLS device's: `device_ca` is the dial's `server_ca`.
    pub(crate) client: super::TlsDevice,
    /// The role of a server certificate that carries none; `None`: refused.
    pub(crate) default_role: Option<String>,
}

impl Setting for Option<TlsDial> {
    const KIND: ValueKind = ValueKind::List;
    fn read(raw: &Raw, _check: &Check) -> Result<Self, ValueError> {
        let not_table = "expected a table: { cert = ..., key = ..., server_ca = ... }";
        let (t, given) = read_table(raw, DIAL_TLS_KEYS, not_table)?;
        let ca = (
            "server_ca",
            "the CA the server's certificate must chain to (PEM)",
        );
        let files = (t.cert, t.key, t.server_ca);
        Ok(Some(TlsDial {
            client: super::access::tls_client(&given, "server", ca, files, t.server_name)?,
            default_role: given.contains(&"default_role").then_some(t.default_role),
        }))
    }
    fn print(&self) -> String {
        let Some(t) = self else {
            return "{}".into();
        };
        let mut parts = super::access::client_parts(&t.client, "server_ca");
        if let Some(r) = &t.default_role {
            parts.push(format!("default_role = {}", r.print()));
        }
        format!("{{ {} }}", parts.join(", "))
    }
}

/// Bytes a dial sends of its own: `"site-17"` (the text's UTF-8), or `"hex:53 31"`
/// (hex digits, spaces between bytes allowed). Empty: none.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Payload(pub(crate) Vec<u8>);

/// The most bytes an identity or heartbeat may have: one TCP segment's worth, well
/// inside what every server reads at once.
const PAYLOAD_MAX: usize = 1024;

impl Setting for Payload {
    const KIND: ValueKind = ValueKind::Str;
    fn read(raw: &Raw, check: &Check) -> Result<Self, ValueError> {
        let s = String::read(raw, check)?;
        let bytes = match s.strip_prefix("hex:") {
            Some(hex) => {
                let digits: String = hex.chars().filter(|c| !c.is_whitespace()).collect();
                let bad = || {
                    format!("expected hex digits after \"hex:\", like \"hex:0a ff\", got {hex:?}")
                };
                if !digits.len().is_multiple_of(2) || !digits.chars().all(|c| c.is_ascii_hexdigit())
                {
                    return Err(bad().into());
                }
                (0..digits.len())
                    .step_by(2)
                    .map(|i| u8::from_str_radix(&digits[i..i + 2], 16).map_err(|_| bad()))
                    .collect::<Result<Vec<u8>, String>>()?
            }
            None => s.into_bytes(),
        };
        if bytes.is_empty() {
            return Err("must not be empty (leave the key out to send nothing)".into());
        }
        if bytes.len() > PAYLOAD_MAX {
            return Err(format!("{} bytes: at most {PAYLOAD_MAX}", bytes.len()).into());
        }
        Ok(Self(bytes))
    }
    fn print(&self) -> String {
        let text = std::str::from_utf8(&self.0).ok().filter(|t| {
            !t.starts_with("hex:") && t.chars().all(|c| c.is_ascii_graphic() || c == ' ')
        });
        match text {
            Some(t) => t.to_owned().print(),
            None => {
                let hex: Vec<String> = self.0.iter().map(|b| format!("{b:02x}")).collect();
                format!("\"hex:{}\"", hex.join(" "))
            }
        }
    }
}

/// One master mbgate dials, checked.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct DialConfig {
    /// `host:port`, resolved at each attempt.
    pub(crate) address: String,
    pub(crate) framing: ListenFraming,
    /// What its requests may do.
    pub(crate) policy: Policy,
    pub(crate) priority: u8,
    /// Sent once at each connect; empty: nothing.
    pub(crate) identity: Vec<u8>,
    /// Sent after `heartbeat_ms` without a request; empty: nothing.
    pub(crate) heartbeat: Vec<u8>,
    pub(crate) heartbeat_ms: u64,
    pub(crate) backoff_min_ms: u64,
    pub(crate) backoff_max_ms: u64,
    pub(crate) connect_timeout_ms: u64,
    pub(crate) idle_timeout_ms: u64,
    /// Modbus/TCP Security, mbgate the client.
    pub(crate) tls: Option<TlsDial>,
}

impl DialConfig {
    /// Its requests as a listener's masters' are taken (the one connection type of
    /// `crate::masters::tcp`): the framing, what they may do, the priority class and the idle
    /// timeout; a dialed connection has no allow list (mbgate chose the peer).
    pub(crate) fn masters(&self) -> ListenConfig {
        ListenConfig {
            tcp: TcpConfig {
                listen: SocketAddr::from(([0, 0, 0, 0], 0)),
                max_connections: 1,
                idle_timeout_ms: self.idle_timeout_ms,
            },
            framing: self.framing,
            access: super::ListenAccess {
                allow: None,
                policy: self.policy.clone(),
                tls: None,
            },
            priority: self.priority,
            transport: super::Transport::Tcp,
            notifications: false,
        }
    }

    fn table(&self) -> DialTable {
        let payload = |b: &Vec<u8>| Payload(b.clone());
        DialTable {
            address: HostPort(self.address.clone()),
            framing: self.framing,
            read_only: self.policy.read_only,
            write: WriteRules(self.policy.write.clone()),
            priority: self.priority,
            identity: payload(&self.identity),
            heartbeat: payload(&self.heartbeat),
            heartbeat_ms: self.heartbeat_ms,
            backoff_min_ms: self.backoff_min_ms,
            backoff_max_ms: self.backoff_max_ms,
            connect_timeout_ms: self.connect_timeout_ms,
            idle_timeout_ms: self.idle_timeout_ms,
            tls: self.tls.clone(),
        }
    }
}

/// The `[[dial]]` tables, read by [`DIAL_KEYS`]; `path` is what messages call them
/// (`dial`).
pub(super) fn dials(raw: &Raw, path: &str) -> Result<Vec<DialConfig>, ValueError> {
    let Raw::List(tables) = raw else {
        return Err("expected [[dial]] tables".into());
    };
    let mut out = Vec::new();
    for (i, t) in tables.iter().enumerate() {
        let here = format!("{path}[{i}]");
        let one = || -> Result<DialConfig, ValueError> {
            let (t, given) = read_table(t, DIAL_KEYS, "expected a table ([[dial]])")?;
            if !given.contains(&"address") {
                let m = "missing: host:port of the master's server mbgate connects to";
                return Err(ValueError::new(m).value("address"));
            }
            if t.backoff_min_ms > t.backoff_max_ms {
                let m = format!(
                    "{} is more than backoff_max_ms ({}): the first wait would be longer than the longest",
                    t.backoff_min_ms, t.backoff_max_ms
                );
                return Err(ValueError::new(m).value("backoff_min_ms"));
            }
            Ok(DialConfig {
                address: t.address.0,
                framing: t.framing,
                policy: policy(t.read_only, t.write, &here)?,
                priority: t.priority,
                identity: t.identity.0,
                heartbeat: t.heartbeat.0,
                heartbeat_ms: t.heartbeat_ms,
                backoff_min_ms: t.backoff_min_ms,
                backoff_max_ms: t.backoff_max_ms,
                connect_timeout_ms: t.connect_timeout_ms,
                idle_timeout_ms: t.idle_timeout_ms,
                tls: t.tls,
            })
        };
        out.push(one().map_err(|e| e.item(i))?);
    }
    Ok(out)
}

/// The `[[dial]]` tables as the file writes them: each key that is not its default.
pub(super) fn to_toml(dials: &[DialConfig]) -> String {
    let defaults = DialTable::default();
    let mut out = String::new();
    for d in dials {
        let t = d.table();
        out += "\n[[dial]]\n";
        for k in DIAL_KEYS {
            let value = (k.get)(&t);
            if k.name == "address" || value != (k.get)(&defaults) {
                out += &format!("{} = {value}\n", k.name);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use crate::config::parse;

    #[test]
    fn a_dial_is_read_checked_and_printed_back() {
        let cfg = parse(
            "[[dial]]\naddress = \"scada.example.net:502\"\nidentity = \"site-17\"\n\
             heartbeat = \"hex:ff fe 00\"\nread_only = true\nbackoff_max_ms = 5000\n\
             tls = { cert = \"g.pem\", key = \"g.key\", server_ca = \"ca.pem\", default_role = \"viewer\" }\n\
             [[role]]\nname = \"viewer\"\nread_only = true\n",
            "t.toml",
        )
        .unwrap();
        let d = &cfg.dials[0];
        assert_eq!(d.address, "scada.example.net:502");
        assert_eq!(d.identity, b"site-17");
        assert_eq!(d.heartbeat, [0xff, 0xfe, 0x00]);
        assert!(d.policy.read_only);
        assert_eq!((d.backoff_min_ms, d.backoff_max_ms), (1000, 5000));
        let printed = crate::config::to_toml(&cfg);
        assert_eq!(parse(&printed, "printed").unwrap(), cfg, "{printed}");
        assert!(
            printed.contains("heartbeat = \"hex:ff fe 00\""),
            "{printed}"
        );
    }

    #[test]
    fn a_bad_dial_is_refused_at_its_key() {
        let bad = [
            ("[[dial]]\nidentity = \"x\"\n", "dial[0].address"),
            (
                "[[dial]]\naddress = \"h:1\"\nheartbeat = \"hex:0\"\n",
                "dial[0].heartbeat",
            ),
            (
                "[[dial]]\naddress = \"h:1\"\nidentity = \"\"\n",
                "dial[0].identity",
            ),
            (
                "[[dial]]\naddress = \"h:1\"\nbackoff_min_ms = 9000\nbackoff_max_ms = 100\n",
                "dial[0].backoff_min_ms",
            ),
            ("[[dial]]\naddress = \"h:1\"\nretry = 1\n", "dial[0].retry"),
            ("[[dial]]\naddress = \"nohost\"\n", "dial[0].address"),
            (
                "[[dial]]\naddress = \"h:1\"\ntls = { cert = \"a\", key = \"b\" }\n",
                "dial[0].tls.server_ca",
            ),
            (
                "[[dial]]\naddress = \"h:1\"\n\
                 tls = { cert = \"a\", key = \"b\", server_ca = \"c\", default_role = \"x\" }\n",
                "dial[0].tls.default_role",
            ),
        ];
        for (text, key) in bad {
            let e = parse(text, "t.toml").unwrap_err().to_string();
            assert!(e.contains(key), "{text}: {e}");
        }
    }
}
