//! `mbgate capture` (docs/capture.md): the flags made a capture request, then the
//! capture (`crate::gateway::control::capture`). Exit 0 when it ended as asked (`--count`,
//! `--seconds`, Ctrl-C), 1 when it could not run or its output failed, 2 bad
//! arguments.

use super::exit;
use super::signals;
use crate::gateway::control::capture::capture;
use crate::gateway::control::control_socket;
use crate::ops::capture::request::{BadRequest, CaptureRequest, MasterMatch};
use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;

/// Flags that make no capture request; the message names the flag.
#[derive(Debug, thiserror::Error)]
enum BadArgs {
    #[error("--line {0:?}: a line's index or name, without spaces")]
    Line(String),
    #[error("--master: {0}")]
    Master(BadRequest),
    /// The request's words are the flags' (`unit=3` is `--unit 3`).
    #[error("{}", .0.to_string().replace("unit=", "--unit ").replace("function=", "--function "))]
    Request(BadRequest),
}

/// Capture a running gateway's traffic to pcapng, for Wireshark.
#[derive(Debug, clap::Args)]
pub(crate) struct CaptureArgs {
    /// Where to write: a file, or - for standard output (`-o - | wireshark -k -i -`)
    #[arg(long, short = 'o', value_name = "FILE")]
    output: PathBuf,
    /// The gateway's control socket [default: from the configuration file]
    #[arg(long, value_name = "PATH")]
    socket: Option<PathBuf>,
    /// The gateway's configuration file, to find its control socket (control.socket;
    /// empty: the packaged unit's runtime directory for this file)
    /// [default: /etc/mbgate/mbgate.toml]
    #[arg(long, short = 'c', value_name = "FILE")]
    config: Option<PathBuf>,
    /// Only this line: its index (0 is the first [[line]]), its name (/dev/ttyUSB0,
    /// host:port), or tcp for the masters' side; repeat for several
    #[arg(long, value_name = "LINE")]
    line: Vec<String>,
    /// Only this unit id (dropped bytes, which have none, are kept); repeat for several
    #[arg(long, value_name = "ID")]
    unit: Vec<String>,
    /// Only this master's packets, by its address (10.0.0.5) or address and port
    /// (10.0.0.5:40000), and the line's frames for its requests; repeat for several
    #[arg(long, value_name = "ADDR")]
    master: Vec<String>,
    /// Only this function code (decimal or 0x10; its exceptions too); repeat for several
    #[arg(long, value_name = "FC")]
    function: Vec<String>,
    /// Stop after this many packets
    #[arg(long, value_name = "N")]
    count: Option<u64>,
    /// Stop after this many seconds
    #[arg(long, value_name = "S")]
    seconds: Option<u64>,
}

impl CaptureArgs {
    /// The request line these arguments ask for.
    fn request(&self) -> Result<CaptureRequest, BadArgs> {
        let mut words = vec!["capture".to_owned()];
        for l in &self.line {
            if l.is_empty() || l.contains(char::is_whitespace) {
                return Err(BadArgs::Line(l.clone()));
            }
            words.push(format!("line={l}"));
        }
        for u in &self.unit {
            words.push(format!("unit={u}"));
        }
        for m in &self.master {
            MasterMatch::parse(m).map_err(BadArgs::Master)?;
            words.push(format!("master={m}"));
        }
        for f in &self.function {
            words.push(format!("function={f}"));
        }
        if let Some(n) = self.count {
            words.push(format!("count={n}"));
        }
        if let Some(s) = self.seconds {
            words.push(format!("seconds={s}"));
        }
        CaptureRequest::parse(&words.join(" ")).map_err(BadArgs::Request)
    }
}

/// `mbgate capture`.
pub(crate) fn main(args: CaptureArgs) -> ExitCode {
    let request = match args.request() {
        Ok(r) => r,
        Err(e) => {
            eprintln!("mbgate capture: {e}");
            return exit::code(exit::USAGE);
        }
    };
    let to_stdout = args.output.as_os_str() == "-";
    if to_stdout && std::io::stdout().is_terminal() {
        eprintln!(
            "mbgate capture: pcapng is binary: give -o FILE, or pipe it (-o - | wireshark -k -i -)"
        );
        return exit::code(exit::USAGE);
    }
    let socket = match control_socket(args.socket.as_deref(), args.config.as_deref()) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("mbgate capture: {e}");
            return exit::code(exit::USAGE);
        }
    };
    let rt = match signals::runtime(exit::FAILED) {
        Ok(rt) => rt,
        Err(code) => return code,
    };
    let shown = if to_stdout {
        "standard output".to_owned()
    } else {
        args.output.display().to_string()
    };
    match rt.block_on(capture(&socket, &request, &args.output, &shown)) {
        Ok(()) => exit::code(exit::OK),
        Err(e) => {
            eprintln!("mbgate capture: {e}");
            exit::code(exit::FAILED)
        }
    }
}
