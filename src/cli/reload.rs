//! `mbgate reload`: exit 0 taken, 1 refused (the running configuration stays), 3 the
//! gateway could not be asked, 2 bad arguments.

use super::exit;
use crate::gateway::control::control_socket;
use crate::gateway::control::reload::{reload, ReloadAnswer};
use std::path::PathBuf;
use std::process::ExitCode;

/// `mbgate reload`'s flags.
#[derive(Debug, clap::Args)]
pub(crate) struct ReloadArgs {
    /// The gateway's control socket [default: from the configuration file]
    #[arg(long, value_name = "PATH")]
    socket: Option<PathBuf>,
    /// The gateway's configuration file, to find its control socket (control.socket;
    /// empty: the packaged unit's runtime directory for this file)
    /// [default: /etc/mbgate/mbgate.toml]
    #[arg(long, short = 'c', value_name = "FILE")]
    config: Option<PathBuf>,
}

/// `mbgate reload`.
pub(crate) fn main(args: ReloadArgs) -> ExitCode {
    let socket = match control_socket(args.socket.as_deref(), args.config.as_deref()) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("mbgate reload: {e}");
            return exit::code(exit::USAGE);
        }
    };
    match reload(&socket) {
        Ok(ReloadAnswer::Taken(said)) => {
            print!("{said}");
            exit::code(exit::OK)
        }
        Ok(ReloadAnswer::Refused(said)) => {
            eprint!("mbgate reload: {said}");
            exit::code(exit::FAILED)
        }
        Ok(ReloadAnswer::Failed(why)) => {
            eprintln!("mbgate reload: {why}");
            exit::code(exit::OTHER)
        }
        Err(e) => {
            eprintln!(
                "mbgate reload: {e}; `systemctl reload mbgate` (SIGHUP) reloads too, its answer in the log"
            );
            exit::code(exit::OTHER)
        }
    }
}
