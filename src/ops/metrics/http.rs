//! The metrics listener: a minimal HTTP/1.1 server on tokio, GET (and HEAD), one
//! request per connection, then closed; over TLS and behind users when the web
//! configuration file says so (`web/`, docs/watching.md "Behind TLS and a password").
//! Written here rather than taken from a crate: it serves a few read-only paths, and
//! an HTTP crate would bring a large tree for them (docs/architecture.md
//! "Dependencies we kept and why").
//!
//! - `/metrics`: the Prometheus exposition (`expose.rs`).
//! - `/`: the status page, and `/status.json`, what it polls (`page.rs`).
//!
//! Nothing here changes the gateway: whoever can reach the listener may read the
//! numbers, never reconfigure it (`mbgate reload` asks over the control socket,
//! `crate::gateway::control`). With users, every path answers 401 to a request without
//! their credentials, with nothing of the gateway in its body. It runs on a thread of
//! its own at a lower priority ([`spawn`]), so the relay's loop never waits for a
//! scrape to be rendered, a handshake or a password checked. A TLS handshake and
//! then a request head larger than 8 KiB, or slower than 5 s each, are refused; at
//! most 16 connections at once, 8 of them from one source, the others closed at once.

use super::web::login::{Login, Logins};
use super::web::WebAccess;
use super::{expose, page, Board};
use std::net::{IpAddr, SocketAddr};
use std::sync::{Arc, RwLock};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

const MAX_HEAD: usize = 8 * 1024;
const HEAD_WITHIN: Duration = Duration::from_secs(5);
const MAX_CONNECTIONS: usize = 16;
/// Of them, from one source (an IPv4 address, or an IPv6 /64): a peer that holds its
/// connections open without a word leaves the others half the listener.
const PER_SOURCE: usize = 8;
/// The listener's threads' nice value: under load the masters' side, at 0, gets about
/// ten times their share of a core (Linux's CFS weights 1024 against 110).
const NICE: i32 = 10;

/// What the listener serves with (a reload swaps it) and its logins' state (kept
/// across reloads: a reload does not give a source its budget back).
#[derive(Debug, Default)]
pub(crate) struct WebState {
    pub(crate) access: RwLock<Arc<WebAccess>>,
    pub(crate) logins: Logins,
}

impl WebState {
    pub(crate) fn new(access: WebAccess) -> Self {
        WebState {
            access: RwLock::new(Arc::new(access)),
            logins: Logins::default(),
        }
    }

    fn access(&self) -> Arc<WebAccess> {
        self.access.read().expect("not poisoned").clone()
    }
}

/// Binds `addr` for the metrics listener (at start, so a bad address fails the start).
pub(crate) fn bind(addr: SocketAddr) -> std::io::Result<std::net::TcpListener> {
    let listener = std::net::TcpListener::bind(addr)?;
    listener.set_nonblocking(true)?;
    Ok(listener)
}

/// Lowers the calling thread's priority to [`NICE`] (Linux: a nice value is a
/// thread's own). Failing, it says so once and the thread runs as it is.
fn lower_priority() {
    #[allow(unsafe_code)]
    // SAFETY: setpriority(2) takes plain integers; `who` 0 is the calling thread, and
    // raising one's own nice value needs no privilege. Nothing is borrowed.
    let r = unsafe { libc::setpriority(libc::PRIO_PROCESS as _, 0, NICE) };
    if r != 0 {
        debug!(
            "metrics listener: cannot lower its priority: {}",
            std::io::Error::last_os_error()
        );
    }
}

/// Serves `board` on `listener` until `stop`, on a thread of its own with a runtime of
/// its own, at a lower priority (its password checks too): rendering a scrape or the
/// page, a TLS handshake or a bcrypt check never holds up the relay's loop, whose
/// runtime has one thread.
pub(crate) fn spawn(
    listener: std::net::TcpListener,
    board: Arc<Board>,
    web: Arc<WebState>,
    stop: CancellationToken,
) {
    let run = move || {
        lower_priority();
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .on_thread_start(lower_priority)
            .build()?;
        rt.block_on(async {
            let listener = TcpListener::from_std(listener)?;
            serve(listener, board, web, stop).await;
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

/// What the log says of the listener at `local` serving with `access`: where the
/// page and the metrics are, and who may read them.
pub(crate) fn announce(local: SocketAddr, access: &WebAccess) {
    let scheme = access.scheme();
    let how = access.said();
    let file = access
        .file
        .as_ref()
        .map_or_else(String::new, |f| format!(", {}", f.display()));
    // The page's address first: the one a person opens.
    info!(
        "status page on {scheme}://{local}/ (open it in a browser; `mbgate status --metrics {scheme}://{local}` \
         asks it from a shell); Prometheus metrics on {scheme}://{local}/metrics ({how}{file})"
    );
    if local.ip().is_loopback() {
        return;
    }
    if access.users.is_none()
        && !access
            .tls
            .as_ref()
            .is_some_and(|t| t.said.contains("required"))
    {
        warn!(
            "metrics listener on {local}: no users and no client certificates: anyone who reaches it reads \
             every line's numbers and, on the status page, the frames and their register values \
             (metrics.web_config, docs/watching.md \"Behind TLS and a password\")"
        );
    } else if access.users.is_some() && access.tls.is_none() {
        warn!(
            "metrics listener on {local}: its passwords cross the network in clear without TLS \
             (tls_server_config in {})",
            access
                .file
                .as_ref()
                .map_or_else(String::new, |f| f.display().to_string())
        );
    }
}

/// Serves `board` on `listener` until `stop`.
async fn serve(
    listener: TcpListener,
    board: Arc<Board>,
    web: Arc<WebState>,
    stop: CancellationToken,
) {
    if let Ok(local) = listener.local_addr() {
        announce(local, &web.access());
    }
    let limit = Arc::new(Semaphore::new(MAX_CONNECTIONS));
    let sources = Arc::new(SourceSlots::default());
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
        let Some(own) = sources.take(peer.ip()) else {
            debug!(%peer, "metrics: {PER_SOURCE} connections from this source already, closed");
            continue;
        };
        let Ok(slot) = limit.clone().try_acquire_owned() else {
            debug!(%peer, "metrics: too many connections, closed");
            continue;
        };
        let (board, web) = (board.clone(), web.clone());
        tokio::spawn(async move {
            if let Err(e) = answer(stream, peer, &board, &web).await {
                debug!(%peer, "metrics: {e}");
            }
            drop((slot, own));
        });
    }
}

/// The connections open from each source.
#[derive(Debug, Default)]
struct SourceSlots(std::sync::Mutex<std::collections::HashMap<IpAddr, usize>>);

/// A connection of a source, given back when dropped.
struct SourceSlot(Arc<SourceSlots>, IpAddr);

impl SourceSlots {
    fn take(self: &Arc<Self>, ip: IpAddr) -> Option<SourceSlot> {
        let source = crate::access::source_of(ip);
        let mut open = self.0.lock().expect("not poisoned");
        let n = open.entry(source).or_default();
        if *n >= PER_SOURCE {
            return None;
        }
        *n += 1;
        Some(SourceSlot(self.clone(), source))
    }
}

impl Drop for SourceSlot {
    fn drop(&mut self) {
        let mut open = self.0 .0.lock().expect("not poisoned");
        if let Some(n) = open.get_mut(&self.1) {
            *n -= 1;
            if *n == 0 {
                open.remove(&self.1);
            }
        }
    }
}

/// A connection: its TLS handshake, if the listener has TLS, then its one exchange.
async fn answer(
    stream: TcpStream,
    peer: SocketAddr,
    board: &Arc<Board>,
    web: &WebState,
) -> std::io::Result<()> {
    let access = web.access();
    match &access.tls {
        Some(tls) => {
            let acceptor = tokio_rustls::TlsAcceptor::from(tls.config.clone());
            let stream = tokio::time::timeout(HEAD_WITHIN, acceptor.accept(stream))
                .await
                .map_err(|_| std::io::Error::other("no TLS handshake within 5 s"))??;
            exchange(stream, peer.ip(), board, &access, &web.logins).await
        }
        None => exchange(stream, peer.ip(), board, &access, &web.logins).await,
    }
}

/// Reads one request head and answers it.
async fn exchange<S: AsyncRead + AsyncWrite + Unpin>(
    mut stream: S,
    peer: IpAddr,
    board: &Arc<Board>,
    access: &WebAccess,
    logins: &Logins,
) -> std::io::Result<()> {
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
        Ok(Ok(true)) => {
            let login = match &access.users {
                Some(users) => {
                    logins
                        .check(users, authorization(&head).as_deref(), peer)
                        .await
                }
                None => Login::Ok(String::new()),
            };
            match login {
                Login::Ok(_) => respond(&head, board, &access.headers),
                Login::Refused => unauthorized(&access.headers),
                Login::TooMany(wait) => too_many(wait, &access.headers),
            }
        }
        Ok(Err(e)) => return Err(e),
        _ => reply(
            400,
            "text/plain; charset=utf-8",
            "bad request\n".into(),
            false,
            &access.headers,
        ),
    };
    stream.write_all(&response).await?;
    stream.shutdown().await
}

/// The value of the request's `Authorization` header, if any.
fn authorization(head: &[u8]) -> Option<String> {
    let text = String::from_utf8_lossy(head);
    text.lines().skip(1).find_map(|l| {
        let (name, value) = l.split_once(':')?;
        name.trim()
            .eq_ignore_ascii_case("authorization")
            .then(|| value.trim().to_owned())
    })
}

/// 401: who asks for the user and password, and nothing else.
fn unauthorized(headers: &[(&'static str, String)]) -> Vec<u8> {
    let mut extra = headers.to_vec();
    extra.push((
        "WWW-Authenticate",
        "Basic realm=\"mbgate metrics\", charset=\"UTF-8\"".into(),
    ));
    reply(
        401,
        "text/plain; charset=utf-8",
        "401 Unauthorized: a user and password are needed here\n".into(),
        false,
        &extra,
    )
}

/// 429: too many logins from this source (or all of them) were checked lately.
fn too_many(wait: Duration, headers: &[(&'static str, String)]) -> Vec<u8> {
    let secs = wait.as_secs().max(1);
    let mut extra = headers.to_vec();
    extra.push(("Retry-After", secs.to_string()));
    reply(
        429,
        "text/plain; charset=utf-8",
        format!("429 Too Many Requests: too many logins lately; try again in {secs} s\n"),
        false,
        &extra,
    )
}

/// The response to a request head.
fn respond(head: &[u8], board: &Arc<Board>, headers: &[(&'static str, String)]) -> Vec<u8> {
    let text = String::from_utf8_lossy(head);
    let mut words = text.lines().next().unwrap_or("").split_whitespace();
    let (method, target) = (words.next().unwrap_or(""), words.next().unwrap_or(""));
    let head_only = method == "HEAD";
    if method != "GET" && !head_only {
        return reply(
            405,
            "text/plain; charset=utf-8",
            "GET only\n".into(),
            false,
            headers,
        );
    }
    let path = target.split('?').next().unwrap_or("");
    match path {
        "/metrics" => reply(
            200,
            expose::CONTENT_TYPE,
            expose::render(board),
            head_only,
            headers,
        ),
        "/" => reply(
            200,
            "text/html; charset=utf-8",
            page::HTML.into(),
            head_only,
            headers,
        ),
        "/status.json" => reply(
            200,
            "application/json",
            page::json(board),
            head_only,
            headers,
        ),
        _ => reply(
            404,
            "text/plain; charset=utf-8",
            "not found: try /metrics\n".into(),
            head_only,
            headers,
        ),
    }
}

fn reply(
    status: u16,
    content_type: &str,
    body: String,
    head_only: bool,
    headers: &[(&'static str, String)],
) -> Vec<u8> {
    let reason = match status {
        200 => "OK",
        400 => "Bad Request",
        401 => "Unauthorized",
        404 => "Not Found",
        429 => "Too Many Requests",
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
    for (name, value) in headers {
        out += &format!("{name}: {value}\r\n");
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
        String::from_utf8(respond(head.as_bytes(), &Arc::new(Board::default()), &[])).unwrap()
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
