//! The metrics listener: a minimal HTTP/1.1 server on tokio, GET (and HEAD), one
//! request per connection, then closed. Written here rather than taken from a crate:
//! it serves a few read-only paths, and an HTTP crate would bring a large tree for
//! them (docs/architecture.md "Dependencies we kept and why").
//!
//! - `/metrics`: the Prometheus exposition (`expose.rs`).
//! - `/`: the status page, and `/status.json`, what it polls (`page.rs`).
//!
//! Nothing here changes the gateway: whoever can reach the listener may read the
//! numbers, never reconfigure it (`mbgate reload` asks over the control socket,
//! `crate::ops::control`). It runs on a thread of its own ([`spawn`]), so the
//! relay's loop never waits for a scrape to be rendered. A request head larger than
//! 8 KiB, or slower than 5 s, is refused; at most 16 connections at once, the others
//! closed at once.

use super::{expose, page, Board};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info};

const MAX_HEAD: usize = 8 * 1024;
const HEAD_WITHIN: Duration = Duration::from_secs(5);
const MAX_CONNECTIONS: usize = 16;

/// Binds `addr` for the metrics listener (at start, so a bad address fails the start).
pub(crate) fn bind(addr: SocketAddr) -> std::io::Result<std::net::TcpListener> {
    let listener = std::net::TcpListener::bind(addr)?;
    listener.set_nonblocking(true)?;
    Ok(listener)
}

/// Serves `board` on `listener` until `stop`, on a thread of its own with a runtime of
/// its own: rendering a scrape or the page never holds up the relay's loop, whose
/// runtime has one thread.
pub(crate) fn spawn(listener: std::net::TcpListener, board: Arc<Board>, stop: CancellationToken) {
    let run = move || {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()?;
        rt.block_on(async {
            let listener = TcpListener::from_std(listener)?;
            serve(listener, board, stop).await;
            Ok::<_, std::io::Error>(())
        })
    };
    let spawned = std::thread::Builder::new()
        .name("mbgate-metrics".into())
        .spawn(move || {
            if let Err(e) = run() {
                tracing::error!("metrics listener stopped: {e}");
            }
        });
    if let Err(e) = spawned {
        tracing::error!("cannot start the metrics listener's thread: {e}");
    }
}

/// Serves `board` on `listener` until `stop`.
async fn serve(listener: TcpListener, board: Arc<Board>, stop: CancellationToken) {
    if let Ok(local) = listener.local_addr() {
        // The page's address first: the one a person opens.
        info!(
            "status page on http://{local}/ (open it in a browser; `mbgate status --metrics {local}` \
             asks it from a shell); Prometheus metrics on http://{local}/metrics"
        );
    }
    let limit = Arc::new(Semaphore::new(MAX_CONNECTIONS));
    tokio::spawn(page::sample(board.clone(), stop.clone()));
    loop {
        let accepted = tokio::select! {
            _ = stop.cancelled() => break,
            r = listener.accept() => r,
        };
        let Ok((stream, peer)) = accepted else {
            // Out of descriptors, most likely: the Modbus side matters more.
            tokio::time::sleep(Duration::from_millis(100)).await;
            continue;
        };
        let Ok(slot) = limit.clone().try_acquire_owned() else {
            debug!(%peer, "metrics: too many connections, closed");
            continue;
        };
        let board = board.clone();
        tokio::spawn(async move {
            if let Err(e) = answer(stream, &board).await {
                debug!(%peer, "metrics: {e}");
            }
            drop(slot);
        });
    }
}

/// Reads one request head and answers it.
async fn answer(mut stream: TcpStream, board: &Arc<Board>) -> std::io::Result<()> {
    let mut head = Vec::with_capacity(512);
    let read = tokio::time::timeout(HEAD_WITHIN, async {
        let mut buf = [0u8; 1024];
        while !head.windows(4).any(|w| w == b"\r\n\r\n") && !head.windows(2).any(|w| w == b"\n\n") {
            let n = stream.read(&mut buf).await?;
            if n == 0 {
                return Ok(false);
            }
            head.extend_from_slice(&buf[..n]);
            if head.len() > MAX_HEAD {
                return Ok(false);
            }
        }
        Ok::<_, std::io::Error>(true)
    })
    .await;
    let response = match read {
        Ok(Ok(true)) => respond(&head, board),
        Ok(Err(e)) => return Err(e),
        _ => reply(
            400,
            "text/plain; charset=utf-8",
            "bad request\n".into(),
            false,
        ),
    };
    stream.write_all(&response).await?;
    stream.shutdown().await
}

/// The response to a request head.
fn respond(head: &[u8], board: &Arc<Board>) -> Vec<u8> {
    let text = String::from_utf8_lossy(head);
    let mut words = text.lines().next().unwrap_or("").split_whitespace();
    let (method, target) = (words.next().unwrap_or(""), words.next().unwrap_or(""));
    let head_only = method == "HEAD";
    if method != "GET" && !head_only {
        return reply(405, "text/plain; charset=utf-8", "GET only\n".into(), false);
    }
    let path = target.split('?').next().unwrap_or("");
    match path {
        "/metrics" => reply(200, expose::CONTENT_TYPE, expose::render(board), head_only),
        "/" => reply(
            200,
            "text/html; charset=utf-8",
            page::HTML.into(),
            head_only,
        ),
        "/status.json" => reply(200, "application/json", page::json(board), head_only),
        _ => reply(
            404,
            "text/plain; charset=utf-8",
            "not found: try /metrics\n".into(),
            head_only,
        ),
    }
}

fn reply(status: u16, content_type: &str, body: String, head_only: bool) -> Vec<u8> {
    let reason = match status {
        200 => "OK",
        400 => "Bad Request",
        404 => "Not Found",
        _ => "Method Not Allowed",
    };
    let mut out = format!(
        "HTTP/1.1 {status} {reason}\r\nContent-Type: {content_type}\r\nContent-Length: {}\r\n\
         Cache-Control: no-store\r\nConnection: close\r\n",
        body.len()
    );
    if status == 405 {
        out += "Allow: GET, HEAD\r\n";
    }
    out += "\r\n";
    let mut out = out.into_bytes();
    if !head_only {
        out.extend_from_slice(body.as_bytes());
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ask(head: &str) -> String {
        String::from_utf8(respond(head.as_bytes(), &Arc::new(Board::default()))).unwrap()
    }

    #[test]
    fn get_metrics_head_and_refusals() {
        let r = ask("GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n");
        assert!(r.starts_with("HTTP/1.1 200 OK\r\n"), "{r}");
        assert!(
            r.contains("Content-Type: application/openmetrics-text"),
            "{r}"
        );
        assert!(r.ends_with("# EOF\n"), "{r}");
        let r = ask("HEAD /metrics HTTP/1.1\r\n\r\n");
        assert!(
            r.starts_with("HTTP/1.1 200 OK\r\n") && r.ends_with("\r\n\r\n"),
            "{r}"
        );
        let r = ask("POST /metrics HTTP/1.1\r\n\r\n");
        assert!(
            r.starts_with("HTTP/1.1 405 ") && r.contains("Allow: GET, HEAD"),
            "{r}"
        );
        let r = ask("GET /nothing HTTP/1.1\r\n\r\n");
        assert!(r.starts_with("HTTP/1.1 404 "), "{r}");
    }
}
