//! Reading the metrics listener's web configuration file (docs/watching.md "Behind
//! TLS and a password"): the YAML of Prometheus' exporter-toolkit, so the file an
//! operator writes for node_exporter or Prometheus itself works here as it is. Every
//! key is checked against the format (an unknown one is refused, as exporter-toolkit
//! refuses it) and every value kept with its line and column, so that a wrong hash
//! or a missing certificate is named by file, line and key. Nothing here reads a
//! certificate or checks a hash: that is `mod.rs`, from what this returns.

use super::WebConfigError;
use saphyr::{LoadableYamlNode, MarkedYamlOwned, ScalarOwned, YamlDataOwned};
use std::path::{Path, PathBuf};

/// Where a value is in the file: its key, dotted from the top
/// (`tls_server_config.cert_file`, `basic_auth_users.alice`), 1-based line and column.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct At {
    pub(crate) key: String,
    pub(crate) line: usize,
    pub(crate) column: usize,
}

/// A PEM item: from a file (`cert_file`, relative to the web file's directory as
/// exporter-toolkit has it) or written inline (`cert`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Pem {
    File(PathBuf),
    Inline(String),
}

/// What the server asks of a client's certificate (`client_auth_type`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum ClientAuth {
    /// None asked (`NoClientCert`, the default).
    None,
    /// Verified against `client_ca_file` when given; none may be given
    /// (`VerifyClientCertIfGiven`).
    IfGiven,
    /// Required and verified (`RequireAndVerifyClientCert`).
    Required,
}

/// A TLS version as the file names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub(crate) enum Version {
    Tls12,
    Tls13,
}

/// `tls_server_config`, each value with where it is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct TlsFile {
    pub(crate) cert: (Pem, At),
    pub(crate) key: (Pem, At),
    pub(crate) client_ca: Option<(Pem, At)>,
    pub(crate) client_auth: (ClientAuth, At),
    pub(crate) min_version: Version,
    pub(crate) max_version: Version,
    /// TLS 1.2 suites by their IANA names, in the server's order of preference.
    pub(crate) cipher_suites: Option<(Vec<String>, At)>,
    /// Key exchange groups by Go's names (`X25519`, `CurveP256`).
    pub(crate) curves: Option<(Vec<String>, At)>,
    pub(crate) prefer_server_order: bool,
}

/// The web configuration file as written.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub(crate) struct WebFile {
    pub(crate) tls: Option<TlsFile>,
    /// `basic_auth_users`: each user's name and bcrypt hash, in the file's order.
    pub(crate) users: Vec<(String, String, At)>,
    /// `http_server_config.headers`: extra response headers.
    pub(crate) headers: Vec<(&'static str, String)>,
}

/// The keys exporter-toolkit reads at the top of the file.
const TOP: [&str; 4] = [
    "tls_server_config",
    "http_server_config",
    "basic_auth_users",
    "rate_limit",
];
const TLS_KEYS: [&str; 13] = [
    "cert",
    "key",
    "client_ca",
    "cert_file",
    "key_file",
    "client_ca_file",
    "client_auth_type",
    "client_allowed_sans",
    "min_version",
    "max_version",
    "cipher_suites",
    "prefer_server_cipher_suites",
    "curve_preferences",
];
const HTTP_KEYS: [&str; 2] = ["http2", "headers"];
/// The headers exporter-toolkit lets the file set, with the values it allows (none:
/// any).
const HEADERS: [(&str, &[&str]); 5] = [
    ("Content-Security-Policy", &[]),
    ("X-Frame-Options", &["deny", "sameorigin"]),
    ("X-Content-Type-Options", &["nosniff"]),
    ("X-XSS-Protection", &[]),
    ("Strict-Transport-Security", &[]),
];

/// The file being read: its path (for errors and relative paths) and its text.
/// `tls_server_config`'s keys as read, before they are checked together.
struct TlsRead {
    cert: Option<(Pem, At)>,
    key: Option<(Pem, At)>,
    client_ca: Option<(Pem, At)>,
    client_auth: Option<(ClientAuth, At)>,
    min_version: Version,
    max_version: Version,
    cipher_suites: Option<(Vec<String>, At)>,
    curves: Option<(Vec<String>, At)>,
    prefer_server_order: bool,
    /// Where `min_version` and `max_version` were given.
    versions: Vec<At>,
}

struct WebFileReader<'a> {
    path: &'a Path,
}

type Node = MarkedYamlOwned;

impl WebFileReader<'_> {
    fn at(&self, key: &str, node: &Node) -> At {
        At {
            key: key.to_owned(),
            line: node.span.start.line(),
            column: node.span.start.col() + 1,
        }
    }

    fn error(&self, at: &At, message: impl Into<String>) -> WebConfigError {
        WebConfigError::At {
            file: self.path.to_owned(),
            line: at.line,
            column: at.column,
            key: at.key.clone(),
            message: message.into(),
        }
    }

    /// The keys and values of a mapping (a key of no value, `key:`, is an empty one).
    fn mapping<'n>(
        &self,
        key: &str,
        node: &'n Node,
    ) -> Result<Vec<(String, At, &'n Node)>, WebConfigError> {
        match &node.data {
            YamlDataOwned::Value(ScalarOwned::Null) => Ok(Vec::new()),
            YamlDataOwned::Mapping(m) => {
                let mut out = Vec::new();
                for (k, v) in m {
                    let name = match &k.data {
                        YamlDataOwned::Value(ScalarOwned::String(s)) => s.clone(),
                        YamlDataOwned::Value(ScalarOwned::Integer(i)) => i.to_string(),
                        _ => return Err(self.error(&self.at(key, k), "a key must be a string")),
                    };
                    let dotted = if key.is_empty() {
                        name.clone()
                    } else {
                        format!("{key}.{name}")
                    };
                    let at = self.at(&dotted, k);
                    out.push((name, at, v));
                }
                Ok(out)
            }
            _ => Err(self.error(&self.at(key, node), "expected a mapping (key: value lines)")),
        }
    }

    fn known(&self, name: &str, at: &At, keys: &[&str]) -> Result<(), WebConfigError> {
        if keys.contains(&name) {
            return Ok(());
        }
        Err(self.error(
            at,
            format!("unknown key; expected one of {}", keys.join(", ")),
        ))
    }

    fn string(&self, at: &At, node: &Node) -> Result<String, WebConfigError> {
        let at = At {
            line: node.span.start.line(),
            column: node.span.start.col() + 1,
            ..at.clone()
        };
        match &node.data {
            YamlDataOwned::Value(ScalarOwned::String(s)) => Ok(s.clone()),
            YamlDataOwned::Value(ScalarOwned::Integer(i)) => Ok(i.to_string()),
            YamlDataOwned::Alias(_) => Err(self.error(&at, "an alias is not taken here")),
            _ => Err(self.error(&at, "expected a string")),
        }
    }

    fn boolean(&self, at: &At, node: &Node) -> Result<bool, WebConfigError> {
        match &node.data {
            YamlDataOwned::Value(ScalarOwned::Boolean(b)) => Ok(*b),
            _ => Err(self.error(&self.value_at(at, node), "expected true or false")),
        }
    }

    fn strings(&self, at: &At, node: &Node) -> Result<Vec<String>, WebConfigError> {
        match &node.data {
            YamlDataOwned::Value(ScalarOwned::Null) => Ok(Vec::new()),
            YamlDataOwned::Sequence(items) => items.iter().map(|i| self.string(at, i)).collect(),
            _ => Err(self.error(&self.value_at(at, node), "expected a list (- item lines)")),
        }
    }

    /// `at`'s key at `node`, the value.
    fn value_at(&self, at: &At, node: &Node) -> At {
        At {
            line: node.span.start.line(),
            column: node.span.start.col() + 1,
            ..at.clone()
        }
    }

    /// A path in the file, relative to the file's directory (as exporter-toolkit reads
    /// it).
    fn file(&self, s: &str) -> PathBuf {
        let p = Path::new(s);
        match self.path.parent() {
            Some(dir) if p.is_relative() => dir.join(p),
            _ => p.to_owned(),
        }
    }

    /// `client_auth_type`, in exporter-toolkit's words; those that ask for a
    /// certificate without verifying it are refused.
    fn client_auth(&self, at: &At, v: &Node, vat: &At) -> Result<ClientAuth, WebConfigError> {
        let s = self.string(at, v)?;
        let auth = match s.as_str() {
            "" | "NoClientCert" => ClientAuth::None,
            "VerifyClientCertIfGiven" => ClientAuth::IfGiven,
            "RequireAndVerifyClientCert" => ClientAuth::Required,
            "RequestClientCert" | "RequireAnyClientCert" | "RequireClientCert" => {
                return Err(self.error(
                    vat,
                    format!(
                        "{s} asks for a certificate without verifying it, which proves nothing: \
                         use RequireAndVerifyClientCert (or VerifyClientCertIfGiven) with client_ca_file"
                    ),
                ))
            }
            _ => {
                return Err(self.error(
                    vat,
                    format!(
                        "invalid value {s:?}; expected NoClientCert, VerifyClientCertIfGiven or RequireAndVerifyClientCert"
                    ),
                ))
            }
        };
        Ok(auth)
    }

    /// `min_version` or `max_version`: TLS12 or TLS13.
    fn version(&self, at: &At, v: &Node, vat: &At) -> Result<Version, WebConfigError> {
        let s = self.string(at, v)?;
        let version = match s.as_str() {
            "TLS12" => Version::Tls12,
            "TLS13" => Version::Tls13,
            "TLS10" | "TLS11" => {
                return Err(self.error(
                    vat,
                    format!("{s}: mbgate speaks TLS 1.2 and 1.3 only (rustls has no older version); write TLS12 or TLS13"),
                ))
            }
            _ => {
                return Err(self.error(
                    vat,
                    format!("invalid value {s:?}; expected TLS12 or TLS13"),
                ))
            }
        };
        Ok(version)
    }

    fn tls(&self, node: &Node) -> Result<Option<TlsFile>, WebConfigError> {
        let mut cert = None;
        let mut key = None;
        let mut client_ca = None;
        let mut client_auth = None;
        let mut min_version = Version::Tls12;
        let mut max_version = Version::Tls13;
        let mut cipher_suites = None;
        let mut curves = None;
        let mut prefer_server_order = true;
        let mut versions = Vec::new();
        let entries = self.mapping("tls_server_config", node)?;
        let whole = self.at("tls_server_config", node);
        for (name, at, v) in &entries {
            self.known(name, at, &TLS_KEYS)?;
            let vat = self.value_at(at, v);
            match name.as_str() {
                "cert_file" | "cert" => self.pem(&mut cert, name == "cert", at, v, &vat)?,
                "key_file" | "key" => self.pem(&mut key, name == "key", at, v, &vat)?,
                "client_ca_file" | "client_ca" => {
                    self.pem(&mut client_ca, name == "client_ca", at, v, &vat)?
                }
                "client_auth_type" => {
                    client_auth = Some((self.client_auth(at, v, &vat)?, vat.clone()));
                }
                "min_version" | "max_version" => {
                    let version = self.version(at, v, &vat)?;
                    if name == "min_version" {
                        min_version = version;
                    } else {
                        max_version = version;
                    }
                    versions.push(vat.clone());
                }
                "cipher_suites" => cipher_suites = Some((self.strings(at, v)?, vat)),
                "curve_preferences" => curves = Some((self.strings(at, v)?, vat)),
                "prefer_server_cipher_suites" => prefer_server_order = self.boolean(at, v)?,
                "client_allowed_sans" => {
                    return Err(self.error(
                        &vat,
                        "not supported by mbgate yet: give each client its own certificate from a CA of its own, and that CA as client_ca_file",
                    ))
                }
                _ => unreachable!("a known key"),
            }
        }
        let read = TlsRead {
            cert,
            key,
            client_ca,
            client_auth,
            min_version,
            max_version,
            cipher_suites,
            curves,
            prefer_server_order,
            versions,
        };
        self.tls_file(read, whole)
    }

    /// A PEM key (`cert_file` or `cert`, inline when `inline`) into `slot`, unless
    /// empty; given twice (a file and inline) is an error.
    fn pem(
        &self,
        slot: &mut Option<(Pem, At)>,
        inline: bool,
        at: &At,
        v: &Node,
        vat: &At,
    ) -> Result<(), WebConfigError> {
        let s = self.string(at, v)?;
        if s.trim().is_empty() {
            return Ok(());
        }
        if let Some((_, other)) = slot {
            return Err(self.error(vat, format!("give {} or {}, not both", other.key, at.key)));
        }
        let p = if inline {
            Pem::Inline(s)
        } else {
            Pem::File(self.file(&s))
        };
        *slot = Some((p, vat.clone()));
        Ok(())
    }

    /// The TLS keys as read, checked together: none at all is no TLS.
    fn tls_file(&self, read: TlsRead, whole: At) -> Result<Option<TlsFile>, WebConfigError> {
        let TlsRead {
            cert,
            key,
            client_ca,
            client_auth,
            min_version,
            max_version,
            cipher_suites,
            curves,
            prefer_server_order,
            versions,
        } = read;
        if cert.is_none() && key.is_none() && client_ca.is_none() && client_auth.is_none() {
            // As exporter-toolkit: no TLS at all.
            return Ok(None);
        }
        let missing = |what: &str| {
            self.error(
                &whole,
                format!("{what} missing: TLS needs the certificate and its key"),
            )
        };
        let cert = cert.ok_or_else(|| missing("cert_file"))?;
        let key = key.ok_or_else(|| missing("key_file"))?;
        let client_auth = client_auth.unwrap_or((ClientAuth::None, whole.clone()));
        match (&client_ca, client_auth.0) {
            (Some((_, at)), ClientAuth::None) => {
                return Err(self.error(
                    at,
                    "a client CA without client_auth_type: set client_auth_type: RequireAndVerifyClientCert (or VerifyClientCertIfGiven)",
                ))
            }
            (None, ClientAuth::IfGiven | ClientAuth::Required) => {
                return Err(self.error(
                    &client_auth.1,
                    "client certificates are verified against client_ca_file, which is missing",
                ))
            }
            _ => {}
        }
        if min_version > max_version {
            let at = versions.last().cloned().unwrap_or(whole);
            return Err(self.error(&at, "min_version is above max_version"));
        }
        Ok(Some(TlsFile {
            cert,
            key,
            client_ca,
            client_auth,
            min_version,
            max_version,
            cipher_suites,
            curves,
            prefer_server_order,
        }))
    }

    fn http(&self, node: &Node, file: &mut WebFile) -> Result<(), WebConfigError> {
        for (name, at, v) in self.mapping("http_server_config", node)? {
            self.known(&name, &at, &HTTP_KEYS)?;
            match name.as_str() {
                // mbgate speaks HTTP/1.1 and offers no other: nothing to turn off.
                "http2" => {
                    self.boolean(&at, v)?;
                }
                _ => {
                    for (header, hat, value) in self.mapping(&at.key, v)? {
                        let names: Vec<&str> = HEADERS.iter().map(|(n, _)| *n).collect();
                        let Some((header, allowed)) = HEADERS
                            .iter()
                            .find(|(n, _)| n.eq_ignore_ascii_case(&header))
                        else {
                            return Err(self.error(
                                &hat,
                                format!(
                                    "not a header the file may set; expected one of {}",
                                    names.join(", ")
                                ),
                            ));
                        };
                        let s = self.string(&hat, value)?;
                        if s.is_empty() {
                            continue;
                        }
                        if s.contains(['\r', '\n']) || !s.is_ascii() {
                            return Err(self.error(
                                &self.value_at(&hat, value),
                                "a header value is one line of ASCII",
                            ));
                        }
                        if !allowed.is_empty()
                            && !allowed.iter().any(|a| a.eq_ignore_ascii_case(&s))
                        {
                            return Err(self.error(
                                &self.value_at(&hat, value),
                                format!(
                                    "invalid value {s:?}; expected one of {}",
                                    allowed.join(", ")
                                ),
                            ));
                        }
                        file.headers.push((header, s));
                    }
                }
            }
        }
        Ok(())
    }

    fn users(&self, node: &Node, file: &mut WebFile) -> Result<(), WebConfigError> {
        for (name, at, v) in self.mapping("basic_auth_users", node)? {
            if name.is_empty() || name.contains(':') || name.chars().any(char::is_control) {
                return Err(self.error(
                    &at,
                    "a user name is not empty and has no ':' or control character (Basic authentication sends user:password)",
                ));
            }
            let hash = self.string(&at, v)?;
            file.users.push((name, hash, self.value_at(&at, v)));
        }
        Ok(())
    }
}

/// Reads the web configuration file at `path`.
pub(crate) fn read(path: &Path) -> Result<WebFile, WebConfigError> {
    let text = std::fs::read_to_string(path).map_err(|source| WebConfigError::Read {
        file: path.to_owned(),
        source,
    })?;
    parse(&text, path)
}

/// Reads `text`, the web configuration file at `path`.
pub(crate) fn parse(text: &str, path: &Path) -> Result<WebFile, WebConfigError> {
    let r = WebFileReader { path };
    let docs = MarkedYamlOwned::load_from_str(text).map_err(|e| WebConfigError::At {
        file: path.to_owned(),
        line: e.marker().line(),
        column: e.marker().col() + 1,
        key: String::new(),
        message: format!("not YAML: {}", e.info()),
    })?;
    let mut file = WebFile::default();
    let Some(top) = docs.first() else {
        // Empty, or comments only: plain HTTP and no users, as exporter-toolkit reads it.
        return Ok(file);
    };
    if docs.len() > 1 {
        let at = r.at("", &docs[1]);
        return Err(r.error(&at, "one YAML document only"));
    }
    for (name, at, v) in r.mapping("", top)? {
        r.known(&name, &at, &TOP)?;
        match name.as_str() {
            "tls_server_config" => file.tls = r.tls(v)?,
            "http_server_config" => r.http(v, &mut file)?,
            "basic_auth_users" => r.users(v, &mut file)?,
            _ => {
                return Err(r.error(
                    &at,
                    "not supported by mbgate: logins are limited by the gateway itself (docs/watching.md); remove rate_limit",
                ))
            }
        }
    }
    Ok(file)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn err(text: &str) -> String {
        parse(text, Path::new("/etc/mbgate/web.yml"))
            .unwrap_err()
            .to_string()
    }

    #[test]
    fn the_exporter_toolkit_format_with_each_value_where_it_is() {
        let text = "\
# as node_exporter reads it
tls_server_config:
  cert_file: web.pem
  key_file: /etc/ssl/web.key
  client_auth_type: RequireAndVerifyClientCert
  client_ca_file: ca.pem
  min_version: TLS13
http_server_config:
  http2: false
  headers:
    X-Frame-Options: deny
basic_auth_users:
  prometheus: $2y$10$X0h1gDsPszWURQaxFh.zoubFi6DXncSjhoQNJgRrnGs7EsimhC7zG
";
        let f = parse(text, Path::new("/etc/mbgate/web.yml")).unwrap();
        let tls = f.tls.unwrap();
        assert_eq!(tls.cert.0, Pem::File("/etc/mbgate/web.pem".into()));
        assert_eq!(tls.key.0, Pem::File("/etc/ssl/web.key".into()));
        assert_eq!(
            tls.cert.1,
            At {
                key: "tls_server_config.cert_file".into(),
                line: 3,
                column: 14
            }
        );
        assert_eq!(tls.client_auth.0, ClientAuth::Required);
        assert_eq!(
            (tls.min_version, tls.max_version),
            (Version::Tls13, Version::Tls13)
        );
        assert_eq!(f.headers, [("X-Frame-Options", "deny".to_owned())]);
        let (user, hash, at) = &f.users[0];
        assert_eq!(
            (user.as_str(), &hash[..7], at.line),
            ("prometheus", "$2y$10$", 13)
        );
        assert_eq!(at.key, "basic_auth_users.prometheus");
        // Nothing at all: plain HTTP, no users.
        assert_eq!(
            parse("# nothing\n", Path::new("w.yml")).unwrap(),
            WebFile::default()
        );
    }

    #[test]
    fn mistakes_are_named_by_file_line_and_key() {
        assert_eq!(
            err("tls_server_config:\n  cert_file: a.pem\n  keyfile: a.key\n"),
            "/etc/mbgate/web.yml:3:3: tls_server_config.keyfile: unknown key; expected one of cert, key, client_ca, cert_file, key_file, client_ca_file, client_auth_type, client_allowed_sans, min_version, max_version, cipher_suites, prefer_server_cipher_suites, curve_preferences"
        );
        assert_eq!(
            err("tls_server_config:\n  cert_file: a.pem\n"),
            "/etc/mbgate/web.yml:2:3: tls_server_config: key_file missing: TLS needs the certificate and its key"
        );
        assert_eq!(
            err("tls_server_config:\n  cert_file: a.pem\n  key_file: a.key\n  min_version: TLS11\n"),
            "/etc/mbgate/web.yml:4:16: tls_server_config.min_version: TLS11: mbgate speaks TLS 1.2 and 1.3 only (rustls has no older version); write TLS12 or TLS13"
        );
        assert!(
            err("tls_server_config:\n  cert_file: a.pem\n  key_file: a.key\n  client_ca_file: ca.pem\n")
                .starts_with("/etc/mbgate/web.yml:4:19: tls_server_config.client_ca_file: a client CA without client_auth_type")
        );
        assert!(err("tls_server_config:\n  cert_file: a\n  key_file: b\n  client_auth_type: RequireAnyClientCert\n")
            .contains(":4:21: tls_server_config.client_auth_type: RequireAnyClientCert asks for a certificate without verifying it"));
        assert_eq!(
            err("basic_auth_users:\n  alice: $2y$10$x\n  alice: $2y$10$y\n"),
            "/etc/mbgate/web.yml:3:3: not YAML: duplicated key in mapping"
        );
        assert_eq!(
            err("basic_auth_users:\n  \"a:b\": x\n"),
            "/etc/mbgate/web.yml:2:3: basic_auth_users.a:b: a user name is not empty and has no ':' or control character (Basic authentication sends user:password)"
        );
        assert!(err("http_server_config:\n  headers:\n    X-Frame-Options: maybe\n")
            .starts_with("/etc/mbgate/web.yml:3:22: http_server_config.headers.X-Frame-Options: invalid value \"maybe\""));
        assert!(err("rate_limit:\n  burst: 3\n")
            .starts_with("/etc/mbgate/web.yml:1:1: rate_limit: not supported"));
        assert!(err("basic_auth_users: [a]\n")
            .starts_with("/etc/mbgate/web.yml:1:19: basic_auth_users: expected a mapping"));
    }
}
