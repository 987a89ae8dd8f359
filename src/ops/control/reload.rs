//! `mbgate reload`: asks a running gateway to read its configuration file again, as
//! SIGHUP does (`systemctl reload`), over its control socket (the one `mbgate capture`
//! uses: root and the gateway's user or group only, docs/design.md §6), and prints
//! what the gateway's log says of it: each change applied, line by line and key by
//! key, what waits for a restart, or why the file was refused (the flags, the printing
//! and the exit code are `crate::cli`'s).

use super::{peer_uid, trust_server, AskError, RELOAD};
use std::io::{Read, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// What the gateway answered.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ReloadAnswer {
    /// Taken: what its log says of it (each change applied, what waits for a restart).
    Taken(String),
    /// Refused (the file does not load, or adds or removes a line): why.
    Refused(String),
    /// It does not reload: why.
    Failed(String),
}

/// Why the gateway could not be asked.
#[derive(Debug, thiserror::Error)]
pub enum ReloadError {
    /// The socket could not be found, reached or trusted.
    #[error(transparent)]
    Ask(#[from] AskError),
    /// It closed without an answer.
    #[error("{} closed without an answer{}", socket.display(), because(.source))]
    Closed {
        /// The socket.
        socket: PathBuf,
        /// The write or read that failed, if one did.
        source: Option<std::io::Error>,
    },
}

fn because(e: &Option<std::io::Error>) -> String {
    e.as_ref().map_or_else(String::new, |e| format!(": {e}"))
}

/// Asks the gateway serving the control socket at `socket` to reload.
pub fn reload(socket: &Path) -> Result<ReloadAnswer, ReloadError> {
    let answer = ask(socket)?;
    let (head, said) = answer.split_once('\n').unwrap_or((answer.as_str(), ""));
    Ok(match head {
        "ok" => ReloadAnswer::Taken(said.to_owned()),
        "refused" => ReloadAnswer::Refused(said.to_owned()),
        other => ReloadAnswer::Failed(other.strip_prefix("error: ").unwrap_or(other).to_owned()),
    })
}

/// `reload` on the control socket at `socket`: the whole answer.
fn ask(socket: &Path) -> Result<String, ReloadError> {
    let mut s = UnixStream::connect(socket).map_err(AskError::connect(socket))?;
    let uid = peer_uid(&s).map_err(AskError::who(socket))?;
    trust_server(uid, socket)?;
    // Reading a file and applying it takes little, but the gateway may be busy.
    s.set_read_timeout(Some(Duration::from_secs(35)))
        .map_err(AskError::Io)?;
    // A gateway that refuses may close before it has read the request: its answer is
    // read even when the request could not be written.
    let sent = s.write_all(format!("{RELOAD}\n").as_bytes());
    let mut all = Vec::new();
    let read = s.read_to_end(&mut all);
    let all = String::from_utf8_lossy(&all).into_owned();
    match (all.is_empty(), sent, read) {
        (false, _, _) => Ok(all),
        (true, Err(e), _) | (true, _, Err(e)) => Err(ReloadError::Closed {
            socket: socket.to_owned(),
            source: Some(e),
        }),
        (true, Ok(()), Ok(_)) => Err(ReloadError::Closed {
            socket: socket.to_owned(),
            source: None,
        }),
    }
}
