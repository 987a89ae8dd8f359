//! `mbgate status`: exit 0 healthy, 1 not (a line's port not open, or a unit not
//! answering), 3 the gateway could not be asked, 2 bad arguments. A password comes
//! from the environment or a file, never from a flag, which `ps` would show anyone.

use super::exit;
use crate::gateway::control::control_socket;
use crate::ops::metrics::status_command::{ask, summarize, turn_on, Asking};
use std::path::PathBuf;
use std::process::ExitCode;

/// Where the password of `--user` is looked for first.
const PASSWORD_ENV: &str = "MBGATE_PASSWORD";

/// The metrics listener asked when nothing else is named.
const DEFAULT_METRICS: &str = "127.0.0.1:9502";

/// `mbgate status`'s flags.
#[derive(Debug, clap::Args)]
pub(crate) struct StatusArgs {
    /// The gateway's metrics listener: ADDR, http://ADDR or https://ADDR (its metrics.listen) [default: over the control socket when there is one, else 127.0.0.1:9502]
    #[arg(long, value_name = "URL")]
    metrics: Option<String>,
    /// https: the CA the gateway's certificate chains to [default: /etc/ssl/certs/ca-certificates.crt]
    #[arg(long, value_name = "FILE")]
    ca: Option<PathBuf>,
    /// https: a client certificate, for a listener that asks for one (with --key)
    #[arg(long, value_name = "FILE", requires = "key")]
    cert: Option<PathBuf>,
    /// https: the key of --cert
    #[arg(long, value_name = "FILE", requires = "cert")]
    key: Option<PathBuf>,
    /// A user of the listener's web configuration; the password from the environment variable MBGATE_PASSWORD or --password-file
    #[arg(long, value_name = "NAME")]
    user: Option<String>,
    /// A file whose first line is the password of --user
    #[arg(long, value_name = "FILE", requires = "user")]
    password_file: Option<PathBuf>,
    /// Ask over the gateway's control socket (root, or the service's user or group; no password) [default: from the configuration file]
    #[arg(long, value_name = "PATH", conflicts_with = "metrics")]
    socket: Option<PathBuf>,
    /// The gateway's configuration file, to find its control socket [default: /etc/mbgate/mbgate.toml]
    #[arg(long, short = 'c', value_name = "FILE", conflicts_with = "metrics")]
    config: Option<PathBuf>,
}

/// The password of `--user`: `--password-file`'s first line, else MBGATE_PASSWORD.
fn password(args: &StatusArgs) -> Result<Option<(String, String)>, String> {
    let Some(user) = &args.user else {
        return Ok(None);
    };
    let password = match &args.password_file {
        Some(f) => {
            let text = std::fs::read_to_string(f)
                .map_err(|e| format!("--password-file {}: {e}", f.display()))?;
            text.lines().next().unwrap_or("").to_owned()
        }
        None => std::env::var(PASSWORD_ENV).map_err(|_| {
            format!("--user {user}: its password goes in the environment variable {PASSWORD_ENV} or in --password-file FILE (never on the command line, where ps shows it)")
        })?,
    };
    Ok(Some((user.clone(), password)))
}

/// `mbgate status`.
pub(crate) fn main(args: StatusArgs) -> ExitCode {
    let login = match password(&args) {
        Ok(l) => l,
        Err(e) => return exit::usage(e),
    };
    let named_socket = args.socket.is_some() || args.config.is_some();
    // Why the control socket, tried first, was passed over for the metrics listener.
    let mut passed_over = None;
    if args.metrics.is_none() {
        let socket = match control_socket(args.socket.as_deref(), args.config.as_deref()) {
            Ok(s) => s,
            Err(e) => return exit::usage(e),
        };
        // Named, or there: asked over it. Else the metrics listener's usual address.
        if named_socket || socket.exists() {
            match crate::gateway::control::status::metrics(&socket) {
                Ok(Ok(text)) => {
                    let (report, healthy) = summarize(&text);
                    print!("{report}");
                    return exit::ok_if(healthy);
                }
                Ok(Err(why)) => {
                    eprintln!("mbgate status: {why}");
                    return exit::code(exit::OTHER);
                }
                // Not ours to use (not root, nor the service's user or group) and not
                // asked for by name: the metrics listener, as before the socket.
                Err(e) if !named_socket => passed_over = Some(e.to_string()),
                Err(e) => {
                    eprintln!("mbgate status: {e}; or ask its metrics listener: mbgate status --metrics ADDR");
                    return exit::code(exit::OTHER);
                }
            }
        }
    }
    let url = args.metrics.unwrap_or_else(|| DEFAULT_METRICS.to_owned());
    let asking = Asking {
        url: url.clone(),
        ca: args.ca,
        cert: args.cert.zip(args.key),
        login,
    };
    match ask(&asking) {
        Ok((report, healthy)) => {
            print!("{report}");
            exit::ok_if(healthy)
        }
        Err(e) => {
            if let Some(why) = passed_over {
                eprintln!("mbgate: not asked over the control socket: {why}");
            }
            eprintln!("mbgate: cannot ask the gateway at {url}: {e}");
            if matches!(e, crate::ops::metrics::status_command::Unreachable::Io(_)) {
                eprint!("{}", turn_on(&url));
            }
            exit::code(exit::OTHER)
        }
    }
}
