//! `mbgate capture` (docs/capture.md): asks a running gateway for a capture over its
//! control socket and writes it to a file or to standard output, until `--count`,
//! `--seconds` or Ctrl-C. On Ctrl-C, or when the output fails (a full disk, a reader
//! that went away), it tells the gateway to stop and reads the capture's end, so the
//! summary on standard error always says how many packets the gateway dropped.

use super::{connect_error, control_socket, peer_uid, trust_server, DATA, END};
use crate::capture::request::{CaptureRequest, MasterMatch};
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::UnixStream;

/// Capture a running gateway's traffic to pcapng, for Wireshark.
#[derive(Debug, clap::Args)]
pub struct CaptureArgs {
    /// Where to write: a file, or - for standard output (`-o - | wireshark -k -i -`)
    #[arg(long, short = 'o', value_name = "FILE")]
    pub output: PathBuf,
    /// The gateway's control socket [default: from the configuration file]
    #[arg(long, value_name = "PATH")]
    pub socket: Option<PathBuf>,
    /// The gateway's configuration file, to find its control socket (control.socket;
    /// empty: the packaged unit's runtime directory for this file)
    /// [default: /etc/mbgate/mbgate.toml]
    #[arg(long, short = 'c', value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Only this line: its index (0 is the first [[line]]), its name (/dev/ttyUSB0,
    /// host:port), or tcp for the masters' side; repeat for several
    #[arg(long, value_name = "LINE")]
    pub line: Vec<String>,
    /// Only this unit id (dropped bytes, which have none, are kept); repeat for several
    #[arg(long, value_name = "ID")]
    pub unit: Vec<String>,
    /// Only this master's packets, by its address (10.0.0.5) or address and port
    /// (10.0.0.5:40000), and the line's frames for its requests; repeat for several
    #[arg(long, value_name = "ADDR")]
    pub master: Vec<String>,
    /// Only this function code (decimal or 0x10; its exceptions too); repeat for several
    #[arg(long, value_name = "FC")]
    pub function: Vec<String>,
    /// Stop after this many packets
    #[arg(long, value_name = "N")]
    pub count: Option<u64>,
    /// Stop after this many seconds
    #[arg(long, value_name = "S")]
    pub seconds: Option<u64>,
}

/// Exit codes: 0 the capture ended as asked, 1 it could not run or its output
/// failed, 2 bad arguments.
const EXIT_FAILED: u8 = 1;
const EXIT_USAGE: u8 = 2;

impl CaptureArgs {
    /// The request line these arguments ask for.
    fn request(&self) -> Result<CaptureRequest, String> {
        let mut words = vec!["capture".to_owned()];
        for l in &self.line {
            if l.is_empty() || l.contains(char::is_whitespace) {
                return Err(format!(
                    "--line {l:?}: a line's index or name, without spaces"
                ));
            }
            words.push(format!("line={l}"));
        }
        for u in &self.unit {
            words.push(format!("unit={u}"));
        }
        for m in &self.master {
            MasterMatch::parse(m).map_err(|e| format!("--master: {e}"))?;
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
        CaptureRequest::parse(&words.join(" ")).map_err(|e| {
            e.replace("unit=", "--unit ")
                .replace("function=", "--function ")
        })
    }
}

/// `mbgate capture`.
pub fn main(args: CaptureArgs) -> ExitCode {
    let request = match args.request() {
        Ok(r) => r,
        Err(e) => {
            eprintln!("mbgate capture: {e}");
            return ExitCode::from(EXIT_USAGE);
        }
    };
    let to_stdout = args.output.as_os_str() == "-";
    if to_stdout && std::io::stdout().is_terminal() {
        eprintln!(
            "mbgate capture: pcapng is binary: give -o FILE, or pipe it (-o - | wireshark -k -i -)"
        );
        return ExitCode::from(EXIT_USAGE);
    }
    let socket = match control_socket(args.socket.as_deref(), args.config.as_deref()) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("mbgate capture: {e}");
            return ExitCode::from(EXIT_USAGE);
        }
    };
    let rt = match crate::runtime::new() {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("mbgate capture: {e}");
            return ExitCode::from(EXIT_FAILED);
        }
    };
    let shown = if to_stdout {
        "standard output".to_owned()
    } else {
        args.output.display().to_string()
    };
    match rt.block_on(capture(&socket, &request, &args.output, &shown)) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("mbgate capture: {e}");
            ExitCode::from(EXIT_FAILED)
        }
    }
}

/// The end of a capture, as the gateway tells it.
#[derive(Debug, Default)]
struct End {
    packets: u64,
    dropped: u64,
    why: String,
}

fn parse_end(text: &str) -> End {
    let mut end = End::default();
    for word in text.split_whitespace() {
        match word.split_once('=') {
            Some(("packets", n)) => end.packets = n.parse().unwrap_or(0),
            Some(("dropped", n)) => end.dropped = n.parse().unwrap_or(0),
            Some(("why", w)) => end.why = w.replace('_', " "),
            _ => {}
        }
    }
    end
}

/// Reads one message: its tag and payload; `None` at the end of the stream.
async fn read_message(rd: &mut (impl AsyncRead + Unpin)) -> std::io::Result<Option<(u8, Vec<u8>)>> {
    let mut head = [0u8; 5];
    match rd.read_exact(&mut head).await {
        Ok(_) => {}
        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => return Ok(None),
        Err(e) => return Err(e),
    }
    let len = u32::from_be_bytes([head[1], head[2], head[3], head[4]]) as usize;
    let mut payload = vec![0u8; len];
    rd.read_exact(&mut payload).await?;
    Ok(Some((head[0], payload)))
}

async fn open_output(path: &Path) -> std::io::Result<Box<dyn AsyncWrite + Unpin>> {
    if path.as_os_str() == "-" {
        Ok(Box::new(tokio::io::stdout()))
    } else {
        Ok(Box::new(tokio::fs::File::create(path).await?))
    }
}

async fn capture(
    socket: &Path,
    request: &CaptureRequest,
    output: &Path,
    shown: &str,
) -> Result<(), String> {
    let stream = UnixStream::connect(socket)
        .await
        .map_err(|e| connect_error(socket, &e))?;
    let uid = peer_uid(&stream)
        .map_err(|e| format!("cannot tell who serves {}: {e}", socket.display()))?;
    trust_server(uid, socket)?;
    let (rd, mut wr) = stream.into_split();
    let mut rd = tokio::io::BufReader::new(rd);
    // A gateway that refuses may close before it has read the request: its answer
    // is read even when the request could not be written.
    let sent = wr.write_all(format!("{request}\n").as_bytes()).await;
    let mut answer = String::new();
    let read = tokio::io::AsyncBufReadExt::read_line(&mut rd, &mut answer).await;
    match (answer.trim_end(), sent, read) {
        ("ok", Ok(()), _) => {}
        ("" | "ok", Err(e), _) | ("", _, Err(e)) => {
            return Err(format!("the gateway closed the control socket: {e}"))
        }
        ("", _, _) => return Err("the gateway closed the control socket without an answer".into()),
        (a, _, _) => return Err(a.strip_prefix("error: ").unwrap_or(a).to_owned()),
    }
    let mut out = open_output(output)
        .await
        .map_err(|e| format!("cannot write {shown}: {e}"))?;
    eprintln!("mbgate capture: capturing to {shown} (Ctrl-C to stop)");
    let mut interrupt = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::interrupt())
        .map_err(|e| e.to_string())?;
    let mut terminate = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .map_err(|e| e.to_string())?;
    // Once stop is sent: the rest is read to its end (and written, unless the
    // output failed).
    let mut stopping = false;
    let mut failed: Option<String> = None;
    let end = loop {
        let msg = tokio::select! {
            m = read_message(&mut rd) => m.map_err(|e| format!("control socket: {e}"))?,
            _ = interrupt.recv() => {
                if stopping {
                    return Err("interrupted twice: stopped at once".into());
                }
                stopping = true;
                let _ = wr.write_all(b"stop\n").await;
                continue;
            }
            _ = terminate.recv(), if !stopping => {
                stopping = true;
                let _ = wr.write_all(b"stop\n").await;
                continue;
            }
        };
        match msg {
            None => {
                return Err("the gateway closed the control socket before the capture's end".into())
            }
            Some((END, text)) => break parse_end(&String::from_utf8_lossy(&text)),
            Some((DATA, bytes)) if failed.is_none() => {
                let mut write = std::pin::pin!(async {
                    out.write_all(&bytes).await?;
                    out.flush().await
                });
                // Ctrl-C while the output is slow: the capture stops once this is
                // written; a second one gives up on it (a reader that never reads).
                let written = loop {
                    tokio::select! {
                        r = &mut write => break r,
                        _ = interrupt.recv() => {
                            if stopping {
                                return Err("interrupted twice: stopped at once".into());
                            }
                            stopping = true;
                            let _ = wr.write_all(b"stop\n").await;
                        }
                    }
                };
                if let Err(e) = written {
                    failed = Some(format!("cannot write {shown}: {e}"));
                    if !stopping {
                        stopping = true;
                        let _ = wr.write_all(b"stop\n").await;
                    }
                }
            }
            Some(_) => {}
        }
    };
    let dropped = match end.dropped {
        0 => "none dropped".to_owned(),
        n => format!("{n} dropped (the reader did not keep up; the gateway was not slowed)"),
    };
    let why = match end.why.as_str() {
        "count" => "the count was reached",
        "seconds" => "the time was up",
        "stopped" => "stopped",
        w => w,
    };
    match failed {
        Some(e) => Err(format!(
            "{e}; the capture stopped after {} packets from the gateway, {dropped} (the gateway goes on)",
            end.packets
        )),
        None => {
            eprintln!(
                "mbgate capture: {} packets to {shown}, {dropped} ({why})",
                end.packets
            );
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_end_reads_back() {
        let e = parse_end("packets=12 dropped=3 why=the_gateway_stopped");
        assert_eq!(
            (e.packets, e.dropped, e.why.as_str()),
            (12, 3, "the gateway stopped")
        );
    }
}
