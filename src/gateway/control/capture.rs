//! `mbgate capture` (docs/capture.md): asks a running gateway for a capture over its
//! control socket and writes it to a file or to standard output, until `--count`,
//! `--seconds` or Ctrl-C. On Ctrl-C, or when the output fails (a full disk, a reader
//! that went away), it tells the gateway to stop and reads the capture's end, so the
//! summary on standard error always says how many packets the gateway dropped.

use super::{peer_uid, trust_server, AskError, DATA, END};
use crate::ops::capture::request::CaptureRequest;
use std::path::Path;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::unix::{OwnedReadHalf, OwnedWriteHalf};
use tokio::net::UnixStream;

/// Why a capture could not run, or its output failed.
#[derive(Debug, thiserror::Error)]
pub(crate) enum CaptureError {
    /// The socket could not be reached or trusted.
    #[error(transparent)]
    Ask(#[from] AskError),
    /// The gateway closed the socket before it answered the request.
    #[error("the gateway closed the control socket: {0}")]
    Closed(std::io::Error),
    /// The gateway closed the socket without a word.
    #[error("the gateway closed the control socket without an answer")]
    Silent,
    /// The gateway refused the capture: why.
    #[error("{0}")]
    Refused(String),
    /// The output could not be opened.
    #[error("cannot write {shown}: {source}")]
    Output {
        /// The output, as said to the user.
        shown: String,
        /// Why.
        source: std::io::Error,
    },
    /// The signal handlers could not be installed.
    #[error("{0}")]
    Signals(std::io::Error),
    /// Reading the socket failed.
    #[error("control socket: {0}")]
    Socket(std::io::Error),
    /// A second Ctrl-C.
    #[error("interrupted twice: stopped at once")]
    Interrupted,
    /// The gateway closed the socket before the capture's end.
    #[error("the gateway closed the control socket before the capture's end")]
    Cut,
    /// Writing the output failed: the capture stopped, the gateway goes on.
    #[error("cannot write {shown}: {source}; the capture stopped after {packets} packets from the gateway, {dropped} (the gateway goes on)")]
    Failed {
        /// The output, as said to the user.
        shown: String,
        /// Why.
        source: std::io::Error,
        /// Packets the gateway sent.
        packets: u64,
        /// What it dropped, said.
        dropped: String,
    },
}

/// The end of a capture, as the gateway tells it.
#[derive(Debug, Default)]
struct CaptureEnd {
    packets: u64,
    dropped: u64,
    why: String,
}

fn parse_end(text: &str) -> CaptureEnd {
    let mut end = CaptureEnd::default();
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

/// The longest message taken from the gateway: far above any it sends (its packets go
/// in messages of about a MiB, `serve.rs` `MESSAGE_SOFT`). A longer length is no
/// gateway's: refused, never allocated.
const MAX_MESSAGE: usize = 64 << 20;

/// The gateway's messages as they come off the socket. Cancel-safe: what was read
/// stays in `buf` when Ctrl-C wins the `select!`, and the message half read is
/// finished by the next call, never lost (nor the stream's framing with it).
struct Messages<R> {
    rd: R,
    buf: bytes::BytesMut,
}

impl<R: AsyncRead + Unpin> Messages<R> {
    fn new(rd: R) -> Self {
        Messages {
            rd,
            buf: bytes::BytesMut::new(),
        }
    }

    /// The next message: its tag and payload; `None` at the end of the stream.
    async fn next(&mut self) -> std::io::Result<Option<(u8, Vec<u8>)>> {
        use std::io::{Error, ErrorKind};
        loop {
            if let Some(head) = self.buf.get(..5) {
                let len = u32::from_be_bytes([head[1], head[2], head[3], head[4]]) as usize;
                if len > MAX_MESSAGE {
                    return Err(Error::new(
                        ErrorKind::InvalidData,
                        format!("a message of {len} bytes, over {MAX_MESSAGE}: not the gateway's"),
                    ));
                }
                if self.buf.len() >= 5 + len {
                    let msg = self.buf.split_to(5 + len);
                    return Ok(Some((msg[0], msg[5..].to_vec())));
                }
                self.buf.reserve(5 + len - self.buf.len());
            }
            if self.rd.read_buf(&mut self.buf).await? == 0 {
                return match self.buf.is_empty() {
                    true => Ok(None),
                    false => Err(Error::new(
                        ErrorKind::UnexpectedEof,
                        "the gateway closed the socket inside a message",
                    )),
                };
            }
        }
    }
}

async fn open_output(path: &Path) -> std::io::Result<Box<dyn AsyncWrite + Unpin>> {
    if path.as_os_str() == "-" {
        Ok(Box::new(tokio::io::stdout()))
    } else {
        Ok(Box::new(tokio::fs::File::create(path).await?))
    }
}

/// Captures what `request` asks for from the gateway at `socket` into `output` (`-`:
/// standard output, `shown` as said), until its end or SIGINT/SIGTERM (which ask the
/// gateway to stop; a second SIGINT gives up at once), and says on stderr how many
/// packets and drops.
pub(crate) async fn capture(
    socket: &Path,
    request: &CaptureRequest,
    output: &Path,
    shown: &str,
) -> Result<(), CaptureError> {
    let (rd, wr) = ask(socket, request).await?;
    let mut out = open_output(output)
        .await
        .map_err(|source| CaptureError::Output {
            shown: shown.to_owned(),
            source,
        })?;
    eprintln!("mbgate capture: capturing to {shown} (Ctrl-C to stop)");
    let mut stop = Stop {
        wr,
        stopping: false,
    };
    let (end, failed) = copy(Messages::new(rd), &mut *out, &mut stop).await?;
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
        Some(source) => Err(CaptureError::Failed {
            shown: shown.to_owned(),
            source,
            packets: end.packets,
            dropped,
        }),
        None => {
            eprintln!(
                "mbgate capture: {} packets to {shown}, {dropped} ({why})",
                end.packets
            );
            Ok(())
        }
    }
}

/// Sends `request` to the gateway at `socket` (trusted first): the socket's halves once
/// the gateway said `ok`.
async fn ask(
    socket: &Path,
    request: &CaptureRequest,
) -> Result<(tokio::io::BufReader<OwnedReadHalf>, OwnedWriteHalf), CaptureError> {
    let stream = UnixStream::connect(socket)
        .await
        .map_err(AskError::connect(socket))?;
    let uid = peer_uid(&stream).map_err(AskError::who(socket))?;
    trust_server(uid, socket)?;
    let (rd, mut wr) = stream.into_split();
    let mut rd = tokio::io::BufReader::new(rd);
    // A gateway that refuses may close before it has read the request: its answer
    // is read even when the request could not be written.
    let sent = wr.write_all(format!("{request}\n").as_bytes()).await;
    let mut answer = String::new();
    let read = tokio::io::AsyncBufReadExt::read_line(&mut rd, &mut answer).await;
    match (answer.trim_end(), sent, read) {
        ("ok", Ok(()), _) => Ok((rd, wr)),
        ("" | "ok", Err(e), _) | ("", _, Err(e)) => Err(CaptureError::Closed(e)),
        ("", _, _) => Err(CaptureError::Silent),
        (a, _, _) => Err(CaptureError::Refused(
            a.strip_prefix("error: ").unwrap_or(a).to_owned(),
        )),
    }
}

/// The gateway asked to stop, once: the rest is read to its end (and written,
/// unless the output failed).
struct Stop {
    wr: OwnedWriteHalf,
    stopping: bool,
}

impl Stop {
    async fn stop(&mut self) {
        if !self.stopping {
            self.stopping = true;
            let _ = self.wr.write_all(b"stop\n").await;
        }
    }
}

/// Writes the capture's packets to `out` until its end: the end, and how the output
/// failed if it did.
async fn copy<R: AsyncRead + Unpin>(
    mut messages: Messages<R>,
    out: &mut (dyn AsyncWrite + Unpin),
    stop: &mut Stop,
) -> Result<(CaptureEnd, Option<std::io::Error>), CaptureError> {
    let mut interrupt = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::interrupt())
        .map_err(CaptureError::Signals)?;
    let mut terminate = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .map_err(CaptureError::Signals)?;
    let mut failed: Option<std::io::Error> = None;
    loop {
        let msg = tokio::select! {
            m = messages.next() => m.map_err(CaptureError::Socket)?,
            _ = interrupt.recv() => {
                if stop.stopping {
                    return Err(CaptureError::Interrupted);
                }
                stop.stop().await;
                continue;
            }
            _ = terminate.recv(), if !stop.stopping => {
                stop.stop().await;
                continue;
            }
        };
        match msg {
            None => return Err(CaptureError::Cut),
            Some((END, text)) => return Ok((parse_end(&String::from_utf8_lossy(&text)), failed)),
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
                            if stop.stopping {
                                return Err(CaptureError::Interrupted);
                            }
                            stop.stop().await;
                        }
                    }
                };
                if let Err(e) = written {
                    failed = Some(e);
                    stop.stop().await;
                }
            }
            Some(_) => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A message half read when Ctrl-C wins the `select!` is finished by the next
    /// read: nothing of it is lost, and the one after it is read whole.
    #[tokio::test]
    async fn a_message_half_read_when_interrupted_is_read_whole_after() {
        use tokio::io::AsyncWriteExt;
        let (mut gw, client) = tokio::io::duplex(64);
        let mut messages = Messages::new(client);
        let mut first = Vec::new();
        crate::gateway::control::message(&mut first, DATA, &[7; 40]);
        gw.write_all(&first[..20]).await.unwrap();
        let cut = tokio::time::timeout(std::time::Duration::from_millis(50), messages.next());
        assert!(cut.await.is_err(), "no whole message yet");
        gw.write_all(&first[20..]).await.unwrap();
        let mut second = Vec::new();
        crate::gateway::control::message(&mut second, END, b"packets=1 dropped=0 why=stopped");
        gw.write_all(&second).await.unwrap();
        drop(gw);
        assert_eq!(messages.next().await.unwrap(), Some((DATA, vec![7; 40])));
        let end = messages.next().await.unwrap().unwrap();
        assert_eq!((end.0, end.1.len()), (END, 31));
        assert_eq!(messages.next().await.unwrap(), None);
    }

    /// A length no gateway sends is refused before anything is allocated for it; a
    /// stream cut inside a message says so.
    #[tokio::test]
    async fn a_huge_or_cut_message_is_an_error() {
        let huge = [DATA, 0xFF, 0xFF, 0xFF, 0xFF];
        let e = Messages::new(&huge[..]).next().await.unwrap_err();
        assert!(e.to_string().contains("not the gateway's"), "{e}");
        let cut = [DATA, 0, 0, 0, 9, 1, 2];
        let e = Messages::new(&cut[..]).next().await.unwrap_err();
        assert_eq!(e.kind(), std::io::ErrorKind::UnexpectedEof);
    }

    #[test]
    fn the_end_reads_back() {
        let e = parse_end("packets=12 dropped=3 why=the_gateway_stopped");
        assert_eq!(
            (e.packets, e.dropped, e.why.as_str()),
            (12, 3, "the gateway stopped")
        );
    }
}
