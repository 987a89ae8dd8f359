//! The control socket (docs/design.md §6, docs/capture.md "The control socket"): a
//! Unix socket in the runtime directory that only root and the service's own user or
//! group may use, where `mbgate capture` asks for a capture and reads it back, and
//! `mbgate reload` asks for a reload (the metrics listener, which may listen on the
//! network and knows no one, never changes the gateway).
//!
//! A reload: the client writes `reload`; the gateway answers `ok` (taken) or
//! `refused`, then the lines its log says of it, and closes (`error: why` when the
//! gateway does not reload).
//!
//! A status: the client writes `status`; the gateway answers `ok`, then its metrics as
//! the metrics listener's `/metrics` has them, and closes: `mbgate status` on the
//! gateway's own machine needs neither the listener nor a password.
//!
//! A capture: the client writes one request line (`capture/request.rs`); the gateway
//! answers `ok` or `error: why` on a line of its own (and closes, for an error).
//! Then messages, each a tag byte and a 32-bit big-endian length: `D` pcapng bytes
//! (the section and interface headers first, then packets), `E` the end, a line of
//! `key=value` words (`packets`, `dropped`, `why`). The client may write `stop` at
//! any time; the gateway then takes no more packets, writes those it had taken for
//! the capture before it, and the end. A message is at most about a MiB of packets
//! (`serve.rs` `MESSAGE_SOFT`); the client refuses one past 64 MiB.
//!
//! Access is the file's mode (0660: its owner and group), checked again on each
//! connection by the peer's credentials (`SO_PEERCRED`): root, the gateway's own
//! user, or a member of its group. A malformed request closes that client only. The
//! socket is made only in a directory no one but the gateway's user (or root) may
//! write, and the two commands believe only a socket served by root, their own user,
//! or that directory's owner ([`trust_server`]; docs/capture.md).
//!
//! Both ends live here: the gateway's (`serve.rs`, started by `start`) and the
//! commands that ask it, `mbgate capture` (`capture.rs`), `mbgate reload`
//! (`reload.rs`) and `mbgate status` (`status.rs`); this file holds what both ends
//! read: the words and messages, where the socket is, and the asking of one word.

pub(crate) mod capture;
pub(crate) mod reload;
mod serve;
pub(crate) mod status;
mod stream;

use crate::config::Config;
use crate::gateway::reload::ReloadHandle;
use crate::ops::capture::Hub;
use std::path::{Path, PathBuf};
use tokio_util::sync::CancellationToken;
use tracing::{debug, warn};

/// Message tags.
pub(crate) const DATA: u8 = b'D';
pub(crate) const END: u8 = b'E';

/// Appends a message.
pub(crate) fn message(out: &mut Vec<u8>, tag: u8, payload: &[u8]) {
    out.push(tag);
    out.extend((payload.len() as u32).to_be_bytes());
    out.extend(payload);
}

/// The request line of `mbgate reload`.
pub(crate) const RELOAD: &str = "reload";

/// The request line of `mbgate status`: the gateway answers `ok`, then its metrics as
/// `/metrics` has them (docs/watching.md), so a local check needs no password.
pub(crate) const STATUS: &str = "status";

/// Where the control socket goes: `control.socket`, else `control.sock` in the
/// runtime directory systemd made for the service (`RUNTIME_DIRECTORY`), else none.
pub(crate) fn socket_path(cfg: &Config) -> Option<PathBuf> {
    let set = cfg.control.socket.trim();
    if !set.is_empty() {
        return Some(PathBuf::from(set));
    }
    let dirs = std::env::var_os("RUNTIME_DIRECTORY")?;
    let first = std::env::split_paths(&dirs).next()?;
    Some(first.join(SOCKET_NAME))
}

/// Where a gateway run by the packaged units keeps its control socket, from the
/// name of its configuration file: `/etc/mbgate/mbgate.toml` is `mbgate.service`'s
/// (`/run/mbgate`), `/etc/mbgate/NAME.toml` is `mbgate@NAME.service`'s
/// (`/run/mbgate@NAME`); both units have `RuntimeDirectory=%N`.
pub(crate) fn packaged_socket(config: &Path) -> PathBuf {
    let stem = config
        .file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or("mbgate");
    let dir = if stem == "mbgate" {
        "mbgate".to_owned()
    } else {
        format!("mbgate@{stem}")
    };
    Path::new("/run").join(dir).join(SOCKET_NAME)
}

/// The control socket's name in the runtime directory.
pub(crate) const SOCKET_NAME: &str = "control.sock";

/// The configuration file of `mbgate.service`.
const PACKAGED_CONFIG: &str = "/etc/mbgate/mbgate.toml";

/// Why `mbgate capture` or `mbgate reload` could not ask the gateway, or would not
/// believe it.
#[derive(Debug, thiserror::Error)]
pub(crate) enum AskError {
    /// The configuration file, read for its `control.socket`.
    #[error("{}: {source}", file.display())]
    ConfigFile {
        /// The file.
        file: PathBuf,
        /// Why it could not be read.
        source: std::io::Error,
    },
    /// Connecting to the socket failed (said for a user by [`connect_error`]).
    #[error("{}", connect_error(socket, source))]
    Connect {
        /// The socket.
        socket: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// Who serves the socket could not be told.
    #[error("cannot tell who serves {}: {source}", socket.display())]
    Who {
        /// The socket.
        socket: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// Whoever serves the socket is not to be trusted as the gateway ([`trust_server`]).
    #[error("{0}")]
    Untrusted(String),
    /// The socket failed.
    #[error("{0}")]
    Io(#[from] std::io::Error),
}

impl AskError {
    fn connect(socket: &Path) -> impl FnOnce(std::io::Error) -> AskError + '_ {
        |source| AskError::Connect {
            socket: socket.to_owned(),
            source,
        }
    }

    fn who(socket: &Path) -> impl FnOnce(std::io::Error) -> AskError + '_ {
        |source| AskError::Who {
            socket: socket.to_owned(),
            source,
        }
    }
}

/// The control socket: `socket` (`--socket`), else the `control.socket` of `config`
/// (`--config`, by default the packaged unit's file), else the packaged unit's for
/// that file. For `mbgate capture` and `mbgate reload`.
///
/// Only `control.socket` is read from the file, and leniently: a file with a mistake
/// elsewhere (just edited, about to be reloaded and refused with the precise error)
/// still names the socket of the gateway running with the file as it was.
pub(crate) fn control_socket(
    socket: Option<&Path>,
    config: Option<&Path>,
) -> Result<PathBuf, AskError> {
    if let Some(s) = socket {
        return Ok(s.to_owned());
    }
    let file = match config {
        Some(f) => f.to_owned(),
        None if Path::new(PACKAGED_CONFIG).exists() => PathBuf::from(PACKAGED_CONFIG),
        None => return Ok(packaged_socket(Path::new(PACKAGED_CONFIG))),
    };
    let text = match crate::config::read_text(&file, crate::config::MAX_FILE) {
        Ok(text) => text,
        Err(source) => return Err(AskError::ConfigFile { file, source }),
    };
    let set = text
        .parse::<toml::Table>()
        .ok()
        .and_then(|t| Some(t.get("control")?.get("socket")?.as_str()?.trim().to_owned()))
        .unwrap_or_default();
    if set.is_empty() {
        Ok(packaged_socket(&file))
    } else {
        Ok(PathBuf::from(set))
    }
}

/// Why a gateway asked over its control socket gave no answer.
#[derive(Debug, thiserror::Error)]
pub(crate) enum NoAnswer {
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

/// `request` on the control socket at `socket`, answered within `within`: the whole
/// answer, from a gateway [`trust_server`] believes.
pub(crate) fn ask(
    socket: &Path,
    request: &str,
    within: std::time::Duration,
) -> Result<String, NoAnswer> {
    use std::io::{Read, Write};
    let mut s =
        std::os::unix::net::UnixStream::connect(socket).map_err(AskError::connect(socket))?;
    let uid = peer_uid(&s).map_err(AskError::who(socket))?;
    trust_server(uid, socket)?;
    s.set_read_timeout(Some(within)).map_err(AskError::Io)?;
    // A gateway that refuses may close before it has read the request: its answer is
    // read even when the request could not be written.
    let sent = s.write_all(format!("{request}\n").as_bytes());
    let mut all = Vec::new();
    let read = s.read_to_end(&mut all);
    let all = String::from_utf8_lossy(&all).into_owned();
    match (all.is_empty(), sent, read) {
        (false, _, _) => Ok(all),
        (true, Err(e), _) | (true, _, Err(e)) => Err(NoAnswer::Closed {
            socket: socket.to_owned(),
            source: Some(e),
        }),
        (true, Ok(()), Ok(_)) => Err(NoAnswer::Closed {
            socket: socket.to_owned(),
            source: None,
        }),
    }
}

/// This process's effective user and group: the gateway's own at its end of the
/// socket, the user's at `mbgate capture`'s and `mbgate reload`'s.
pub(crate) fn own_ids() -> (u32, u32) {
    #[allow(unsafe_code)]
    // SAFETY: geteuid(2) and getegid(2) have no preconditions and cannot fail.
    unsafe {
        (libc::geteuid(), libc::getegid())
    }
}

/// Is whoever serves the control socket at `socket` (its process runs as `peer_uid`,
/// from the kernel's `SO_PEERCRED`) to be trusted as the gateway, before `mbgate
/// reload` or `mbgate capture` believes a word of it? Root, the user running the
/// command, or the owner of the socket's directory when that directory only its owner
/// may write (systemd's RuntimeDirectory, owned by the service's user): there no one
/// else can have put a socket. Anyone else is an impostor: a socket planted in a
/// directory others may write.
pub(crate) fn trust_server(peer_uid: u32, socket: &Path) -> Result<(), AskError> {
    use std::os::unix::fs::MetadataExt;
    let (me, _) = own_ids();
    if peer_uid == 0 || peer_uid == me {
        return Ok(());
    }
    let dir = match socket.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let s = socket.display();
    match std::fs::metadata(dir) {
        Ok(m) if m.uid() == peer_uid && m.mode() & 0o022 == 0 => Ok(()),
        Ok(m) => Err(AskError::Untrusted(format!(
            "{s} is served by user {peer_uid}, who is neither root, you, nor the owner of {} (owned by user {}, mode {:04o}): not the gateway; its answer is not trusted (a socket another user put there?)",
            dir.display(),
            m.uid(),
            m.mode() & 0o7777
        ))),
        Err(e) => Err(AskError::Untrusted(format!(
            "{s} is served by user {peer_uid}, neither root nor you, and its directory cannot be read ({e}): its answer is not trusted"
        ))),
    }
}

/// The user id of the process at the other end of a Unix socket (`SO_PEERCRED`).
pub(crate) fn peer_uid(socket: &impl std::os::fd::AsRawFd) -> std::io::Result<u32> {
    let mut cred = libc::ucred {
        pid: 0,
        uid: 0,
        gid: 0,
    };
    let mut len = std::mem::size_of::<libc::ucred>() as libc::socklen_t;
    #[allow(unsafe_code)]
    // SAFETY: `cred` and `len` are valid for writes of the size given; the descriptor
    // is open for the borrow of `socket`; getsockopt(2) writes at most `len` bytes.
    let r = unsafe {
        libc::getsockopt(
            socket.as_raw_fd(),
            libc::SOL_SOCKET,
            libc::SO_PEERCRED,
            (&raw mut cred).cast(),
            &raw mut len,
        )
    };
    if r == 0 {
        Ok(cred.uid)
    } else {
        Err(std::io::Error::last_os_error())
    }
}

/// What connecting to `socket` failed with, said for a user.
pub(crate) fn connect_error(socket: &Path, e: &std::io::Error) -> String {
    let s = socket.display();
    match e.kind() {
        std::io::ErrorKind::NotFound => format!(
            "no control socket at {s}: is the gateway running, with this control.socket? \
             (--socket PATH, or --config the gateway's file)"
        ),
        std::io::ErrorKind::PermissionDenied => format!(
            "permission denied on {s}: only root and the gateway's user or group may \
             use it (try sudo)"
        ),
        std::io::ErrorKind::ConnectionRefused => {
            format!("nothing answers on {s}: a socket left by a gateway that stopped?")
        }
        _ => format!("cannot connect to {s}: {e}"),
    }
}

/// Makes the control socket of a gateway of `cfg` and serves it until `shutdown`, if it
/// has a place; one that cannot be made is warned about, and the gateway goes on
/// without. `hub` is where captures come from; `reload` is where reloads go, none if
/// the gateway has no file to read again; `board` the numbers a status is made of.
pub(crate) fn start(
    cfg: &Config,
    hub: &Hub,
    reload: Option<ReloadHandle>,
    board: std::sync::Arc<crate::ops::metrics::Board>,
    shutdown: &CancellationToken,
) {
    match socket_path(cfg) {
        Some(path) => match serve::bind(&path) {
            Ok(c) => {
                let asked = serve::ControlServed {
                    hub: hub.clone(),
                    reload,
                    board,
                };
                tokio::spawn(serve::serve(c, asked, shutdown.clone()));
            }
            Err(e) => warn!(
                "{e}; mbgate capture and mbgate reload are not available (nor mbgate status over it)"
            ),
        },
        None => debug!("no control socket (control.socket is empty, and not under systemd)"),
    }
}

#[cfg(test)]
mod tests;
