//! `mbgate reload`: asks a running gateway to read its configuration file again, as
//! SIGHUP does (`systemctl reload`), through its metrics listener (`POST /reload`,
//! from this machine only), and prints what the gateway's log says of it: each change
//! applied, line by line and key by key, what waits for a restart, or why the file was
//! refused. Exit code: 0 taken, 1 refused, 3 the gateway could not be asked (2: bad
//! arguments, as everywhere).

use std::io::{Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::process::ExitCode;
use std::time::Duration;

/// `mbgate reload`'s flags.
#[derive(Debug, clap::Args)]
pub struct ReloadArgs {
    /// The gateway's metrics listener (its `metrics.listen`, on this machine)
    #[arg(long, value_name = "ADDR", default_value = "127.0.0.1:9502")]
    pub(crate) metrics: String,
}

const EXIT_REFUSED: u8 = 1;
const EXIT_UNREACHABLE: u8 = 3;

/// `mbgate reload`.
pub fn main(args: ReloadArgs) -> ExitCode {
    match ask(&args.metrics) {
        Ok((status, body)) => {
            match status {
                200 => print!("{body}"),
                _ => eprint!("mbgate: {body}"),
            }
            match status {
                200 => ExitCode::SUCCESS,
                409 => ExitCode::from(EXIT_REFUSED),
                _ => ExitCode::from(EXIT_UNREACHABLE),
            }
        }
        Err(e) => {
            eprintln!(
                "mbgate: cannot ask the gateway at {} ({e}); is [metrics] listen set? \
                 `systemctl reload mbgate` (SIGHUP) reloads too, its answer in the log",
                args.metrics
            );
            ExitCode::from(EXIT_UNREACHABLE)
        }
    }
}

/// POST /reload to `addr`: the status code and the body.
fn ask(addr: &str) -> Result<(u16, String), String> {
    let to = addr
        .to_socket_addrs()
        .map_err(|e| e.to_string())?
        .next()
        .ok_or("no address")?;
    let mut s =
        TcpStream::connect_timeout(&to, Duration::from_secs(3)).map_err(|e| e.to_string())?;
    // Reading a file and applying it takes little, but the gateway may be busy.
    s.set_read_timeout(Some(Duration::from_secs(30)))
        .map_err(|e| e.to_string())?;
    write!(
        s,
        "POST /reload HTTP/1.1\r\nHost: {addr}\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
    )
    .map_err(|e| e.to_string())?;
    let mut all = String::new();
    s.read_to_string(&mut all).map_err(|e| e.to_string())?;
    let (head, body) = all.split_once("\r\n\r\n").ok_or("not an HTTP response")?;
    let status = head
        .lines()
        .next()
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|c| c.parse().ok())
        .ok_or("not an HTTP response")?;
    Ok((status, body.to_owned()))
}
