//! Who may read the metrics listener, and over what (docs/watching.md "Behind TLS and
//! a password"): the web configuration file `metrics.web_config` names, in the format
//! of Prometheus' exporter-toolkit (`tls_server_config`, `basic_auth_users` with
//! bcrypt hashes), read whole into a [`WebAccess`] at start and by each reload. Its
//! parts: reading the file with each key's place (`file.rs`), TLS (`tls.rs`), the
//! users and the check of a login (`login.rs`), and how much checking is allowed
//! (`budget.rs`).

pub(crate) mod budget;
pub(crate) mod file;
pub(crate) mod login;
pub(crate) mod tls;

use login::Users;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// A web configuration file that cannot be used: the file, and where in it.
#[derive(Debug, thiserror::Error)]
pub enum WebConfigError {
    /// The file could not be read.
    #[error("{}: cannot read the web configuration file (metrics.web_config): {source}", file.display())]
    Read {
        /// The file.
        file: PathBuf,
        /// What the system said.
        source: std::io::Error,
    },
    /// A value, or the text itself, is wrong.
    #[error("{}:{line}:{column}: {}{message}", file.display(), if key.is_empty() { String::new() } else { format!("{key}: ") })]
    At {
        /// The file.
        file: PathBuf,
        /// 1-based line of the value (or of the key).
        line: usize,
        /// 1-based column.
        column: usize,
        /// The dotted key (`basic_auth_users.alice`), empty where none can be told.
        key: String,
        /// What is wrong.
        message: String,
    },
}

/// What the metrics listener serves with: its TLS, its users, its extra headers.
/// Swapped whole by a reload; a connection keeps the one it began with.
#[derive(Debug, Default)]
pub(crate) struct WebAccess {
    pub(crate) tls: Option<tls::WebTls>,
    pub(crate) users: Option<Arc<Users>>,
    pub(crate) headers: Vec<(&'static str, String)>,
    /// The file it was read from.
    pub(crate) file: Option<PathBuf>,
}

impl WebAccess {
    /// The web configuration file `path` (`metrics.web_config`; empty: none, plain
    /// HTTP for everyone), every certificate and key it names read, every hash checked.
    pub(crate) fn load(path: &str) -> Result<WebAccess, WebConfigError> {
        let path = path.trim();
        if path.is_empty() {
            return Ok(WebAccess::default());
        }
        let path = Path::new(path);
        let read = file::read(path)?;
        let mut users = Vec::new();
        for (name, hash, at) in &read.users {
            let cost = hash
                .parse::<bcrypt::HashParts>()
                .map(|h| h.get_cost())
                .map_err(|e| format!("{e}"))
                .and_then(|cost| {
                    if (4..=31).contains(&cost) {
                        Ok(cost)
                    } else {
                        Err(format!("its cost {cost} is not 4 to 31"))
                    }
                });
            let cost = cost.map_err(|why| WebConfigError::At {
                file: path.to_owned(),
                line: at.line,
                column: at.column,
                key: at.key.clone(),
                message: format!(
                    "not a bcrypt hash ({why}); make one with `htpasswd -nBC 10 \"\" | tr -d ':\\n'` or `mbgate hash-password`"
                ),
            })?;
            users.push((name.clone(), hash.clone(), cost));
        }
        let tls = match &read.tls {
            Some(t) => Some(tls::load(t, path)?),
            None => None,
        };
        Ok(WebAccess {
            tls,
            users: (!users.is_empty()).then(|| Arc::new(Users::new(&users))),
            headers: read.headers,
            file: Some(path.to_owned()),
        })
    }

    /// How the listener is reached, in words: `https`, TLS and who may read
    /// (`TLS 1.2/1.3, 2 users`; `plain HTTP, no users: anyone who reaches it`).
    pub(crate) fn said(&self) -> String {
        let tls = self
            .tls
            .as_ref()
            .map_or_else(|| "plain HTTP".to_owned(), |t| t.said.clone());
        let users = match self.users.as_ref().map(|u| u.len()) {
            None => "no users".to_owned(),
            Some(1) => "1 user (Basic authentication)".to_owned(),
            Some(n) => format!("{n} users (Basic authentication)"),
        };
        format!("{tls}, {users}")
    }

    /// `https` or `http`.
    pub(crate) fn scheme(&self) -> &'static str {
        if self.tls.is_some() {
            "https"
        } else {
            "http"
        }
    }
}

/// Loads the web configuration file `cfg` names, as the gateway would at start: for
/// `mbgate check-config` and before `mbgate run` starts.
pub(crate) fn check(cfg: &crate::config::Config) -> Result<(), WebConfigError> {
    WebAccess::load(&cfg.metrics.web_config).map(|_| ())
}
