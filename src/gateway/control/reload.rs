//! `mbgate reload`: asks a running gateway to read its configuration file again, as
//! SIGHUP does (`systemctl reload`), over its control socket (the one `mbgate capture`
//! uses: root and the gateway's user or group only, docs/design.md §6), and prints
//! what the gateway's log says of it: each change applied, line by line and key by
//! key, what waits for a restart, or why the file was refused (the flags, the printing
//! and the exit code are `crate::cli`'s).

use super::{ask, NoAnswer, RELOAD};
use std::path::Path;
use std::time::Duration;

/// What the gateway answered.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum ReloadAnswer {
    /// Taken: what its log says of it (each change applied, what waits for a restart).
    Taken(String),
    /// Refused (the file does not load, or adds or removes a line): why.
    Refused(String),
    /// It does not reload: why.
    Failed(String),
}

/// Why the gateway could not be asked.
pub(crate) type ReloadError = NoAnswer;

/// Asks the gateway serving the control socket at `socket` to reload.
pub(crate) fn reload(socket: &Path) -> Result<ReloadAnswer, ReloadError> {
    // Reading a file and applying it takes little, but the gateway may be busy.
    let answer = ask(socket, RELOAD, Duration::from_secs(35))?;
    let (head, said) = answer.split_once('\n').unwrap_or((answer.as_str(), ""));
    Ok(match head {
        "ok" => ReloadAnswer::Taken(said.to_owned()),
        "refused" => ReloadAnswer::Refused(said.to_owned()),
        other => ReloadAnswer::Failed(other.strip_prefix("error: ").unwrap_or(other).to_owned()),
    })
}
