//! `mbgate reload`: asks a running gateway to read its configuration file again, as
//! SIGHUP does (`systemctl reload`), over its control socket (the one `mbgate capture`
//! uses: root and the gateway's user or group only, docs/design.md §6), and prints
//! what the gateway's log says of it: each change applied, line by line and key by
//! key, what waits for a restart, or why the file was refused. Exit code: 0 taken, 1
//! refused, 3 the gateway could not be asked (2: bad arguments, as everywhere).

use super::{connect_error, control_socket, peer_uid, trust_server, RELOAD};
use std::io::{Read, Write};
use std::os::unix::net::UnixStream;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

/// `mbgate reload`'s flags.
#[derive(Debug, clap::Args)]
pub struct ReloadArgs {
    /// The gateway's control socket [default: from the configuration file]
    #[arg(long, value_name = "PATH")]
    pub(crate) socket: Option<PathBuf>,
    /// The gateway's configuration file, to find its control socket (control.socket;
    /// empty: the packaged unit's runtime directory for this file)
    /// [default: /etc/mbgate/mbgate.toml]
    #[arg(long, short = 'c', value_name = "FILE")]
    pub(crate) config: Option<PathBuf>,
}

const EXIT_REFUSED: u8 = 1;
const EXIT_UNREACHABLE: u8 = 3;
const EXIT_USAGE: u8 = 2;

/// `mbgate reload`.
pub fn main(args: ReloadArgs) -> ExitCode {
    let socket = match control_socket(args.socket.as_deref(), args.config.as_deref()) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("mbgate reload: {e}");
            return ExitCode::from(EXIT_USAGE);
        }
    };
    let answer = match ask(&socket) {
        Ok(a) => a,
        Err(e) => {
            eprintln!(
                "mbgate reload: {e}; `systemctl reload mbgate` (SIGHUP) reloads too, its answer in the log"
            );
            return ExitCode::from(EXIT_UNREACHABLE);
        }
    };
    let (head, said) = answer.split_once('\n').unwrap_or((answer.as_str(), ""));
    match head {
        "ok" => {
            print!("{said}");
            ExitCode::SUCCESS
        }
        "refused" => {
            eprint!("mbgate reload: {said}");
            ExitCode::from(EXIT_REFUSED)
        }
        other => {
            let why = other.strip_prefix("error: ").unwrap_or(other);
            eprintln!("mbgate reload: {why}");
            ExitCode::from(EXIT_UNREACHABLE)
        }
    }
}

/// `reload` on the control socket at `socket`: the whole answer.
fn ask(socket: &std::path::Path) -> Result<String, String> {
    let mut s = UnixStream::connect(socket).map_err(|e| connect_error(socket, &e))?;
    let uid =
        peer_uid(&s).map_err(|e| format!("cannot tell who serves {}: {e}", socket.display()))?;
    trust_server(uid, socket)?;
    // Reading a file and applying it takes little, but the gateway may be busy.
    s.set_read_timeout(Some(Duration::from_secs(35)))
        .map_err(|e| e.to_string())?;
    // A gateway that refuses may close before it has read the request: its answer is
    // read even when the request could not be written.
    let sent = s.write_all(format!("{RELOAD}\n").as_bytes());
    let mut all = Vec::new();
    let read = s.read_to_end(&mut all);
    let all = String::from_utf8_lossy(&all).into_owned();
    match (all.is_empty(), sent, read) {
        (false, _, _) => Ok(all),
        (true, Err(e), _) | (true, _, Err(e)) => Err(format!(
            "{} closed without an answer: {e}",
            socket.display()
        )),
        (true, Ok(()), Ok(_)) => Err(format!("{} closed without an answer", socket.display())),
    }
}
