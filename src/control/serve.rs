//! The gateway's end of the control socket (the protocol: `control/mod.rs`): the
//! socket made 0660, who may use it (checked again on each connection by the peer's
//! credentials), one client's request read, then a capture streamed from the hub or a
//! reload asked of the gateway and its answer written.

use super::{message, DATA, END, RELOAD};
use crate::capture::hub::{unix_us, Hub, Subscription};
use crate::capture::pcapng;
use crate::capture::request::{Request, MAX_LINE};
use crate::reload::ReloadHandle;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{UnixListener, UnixStream};
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

/// Captures at once; one more is refused with a message.
const MAX_CLIENTS: usize = 8;
/// A client has this long to send its request (`mbgate capture` sends it at once).
const REQUEST_WITHIN: Duration = Duration::from_secs(2);

/// Why the control socket could not be made.
#[derive(Debug, thiserror::Error)]
pub(crate) enum BindError {
    #[error("{0} is in use by another running mbgate (give each its own control.socket)")]
    InUse(PathBuf),
    #[error("cannot make the control socket {path}: {error}")]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
}

/// The socket, bound: removed again when dropped.
pub(crate) struct Control {
    listener: UnixListener,
    path: PathBuf,
}

/// Binds the control socket at `path`, mode 0660. The socket is made under a
/// temporary name, given its mode, then renamed into place, so it is never
/// reachable with a looser mode. A socket left there by a gateway that stopped is
/// replaced; one a running gateway answers on is not.
pub(crate) fn bind(path: &Path) -> Result<Control, BindError> {
    let io = |error| BindError::Io {
        path: path.to_owned(),
        error,
    };
    if std::os::unix::net::UnixStream::connect(path).is_ok() {
        return Err(BindError::InUse(path.to_owned()));
    }
    // Only a socket is ever replaced: a path that names a file by mistake keeps it.
    use std::os::unix::fs::FileTypeExt;
    if let Ok(m) = std::fs::symlink_metadata(path) {
        if !m.file_type().is_socket() {
            return Err(io(std::io::Error::other("it exists and is not a socket")));
        }
    }
    let tmp = path.with_file_name(format!(
        ".{}.{}.tmp",
        path.file_name()
            .and_then(|n| n.to_str())
            .unwrap_or("control"),
        std::process::id()
    ));
    let _ = std::fs::remove_file(&tmp);
    let listener = UnixListener::bind(&tmp).map_err(io)?;
    let placed = std::fs::set_permissions(&tmp, std::fs::Permissions::from_mode(0o660))
        .and_then(|()| std::fs::rename(&tmp, path));
    if let Err(e) = placed {
        let _ = std::fs::remove_file(&tmp);
        return Err(io(e));
    }
    Ok(Control {
        listener,
        path: path.to_owned(),
    })
}

impl Drop for Control {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

/// Serves captures on `control` until `shutdown`; the socket is removed then.
pub(crate) async fn serve(
    control: Control,
    hub: Hub,
    reload: Option<ReloadHandle>,
    shutdown: CancellationToken,
) {
    info!(
        "control socket {} (mbgate capture, mbgate reload)",
        control.path.display()
    );
    let clients = Arc::new(AtomicUsize::new(0));
    loop {
        let (stream, _) = tokio::select! {
            _ = shutdown.cancelled() => break,
            r = control.listener.accept() => match r {
                Ok(a) => a,
                Err(e) => {
                    debug!("control socket accept: {e}");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            },
        };
        if let Err(why) = allowed(&stream) {
            warn!("control socket: {why}; refused");
            let mut s = stream;
            let _ = s.write_all(format!("error: {why}\n").as_bytes()).await;
            continue;
        }
        if clients.fetch_add(1, Ordering::Relaxed) >= MAX_CLIENTS {
            clients.fetch_sub(1, Ordering::Relaxed);
            let mut s = stream;
            let msg = format!("error: {MAX_CLIENTS} captures are running already\n");
            let _ = s.write_all(msg.as_bytes()).await;
            continue;
        }
        let (hub, clients, reload) = (hub.clone(), clients.clone(), reload.clone());
        tokio::spawn(async move {
            client(stream, hub, reload).await;
            clients.fetch_sub(1, Ordering::Relaxed);
        });
    }
    drop(control);
}

/// The gateway's own user and group.
fn own_ids() -> (u32, u32) {
    #[allow(unsafe_code)]
    // SAFETY: geteuid(2) and getegid(2) have no preconditions and cannot fail.
    unsafe {
        (libc::geteuid(), libc::getegid())
    }
}

/// The supplementary groups of process `pid`, from /proc (none if it cannot be read).
fn groups_of(pid: Option<i32>) -> Vec<u32> {
    let Some(pid) = pid else {
        return Vec::new();
    };
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("Groups:"))
        .map(|g| {
            g.split_whitespace()
                .filter_map(|x| x.parse().ok())
                .collect()
        })
        .unwrap_or_default()
}

/// May the peer capture? Root, the gateway's own user, or its group (primary or
/// supplementary). The file's mode lets only those connect; this holds even if the
/// mode was loosened by hand.
fn allowed(stream: &UnixStream) -> Result<(), String> {
    let cred = stream
        .peer_cred()
        .map_err(|e| format!("cannot tell who connected ({e})"))?;
    let (uid, gid) = own_ids();
    let (peer_uid, peer_gid) = (cred.uid(), cred.gid());
    if peer_uid == 0 || peer_uid == uid || peer_gid == gid || groups_of(cred.pid()).contains(&gid) {
        return Ok(());
    }
    Err(format!(
        "user {peer_uid} may not use the control socket: root, or the gateway's user ({uid}) or group ({gid}) only"
    ))
}

/// Reads the request line: at most [`MAX_LINE`] bytes, within [`REQUEST_WITHIN`].
async fn request_line(rd: &mut tokio::net::unix::OwnedReadHalf) -> Result<String, String> {
    let mut line = Vec::new();
    let read = async {
        let mut byte = [0u8; 256];
        loop {
            let n = rd.read(&mut byte).await.map_err(|e| e.to_string())?;
            if n == 0 {
                return Err("closed before its request".to_string());
            }
            line.extend_from_slice(&byte[..n]);
            if let Some(end) = line.iter().position(|&b| b == b'\n') {
                line.truncate(end);
                return Ok(());
            }
            if line.len() > MAX_LINE {
                return Err(format!("a request longer than {MAX_LINE} bytes"));
            }
        }
    };
    match tokio::time::timeout(REQUEST_WITHIN, read).await {
        Err(_) => return Err(format!("no request within {} s", REQUEST_WITHIN.as_secs())),
        Ok(r) => r?,
    }
    String::from_utf8(line).map_err(|_| "a request that is not text".into())
}

/// One client: a reload, or a capture (its request, then packets until a stop
/// condition).
async fn client(stream: UnixStream, hub: Hub, reload: Option<ReloadHandle>) {
    let (mut rd, mut wr) = stream.into_split();
    let line = request_line(&mut rd).await;
    if line
        .as_deref()
        .is_ok_and(|l| l.trim_end_matches('\r') == RELOAD)
    {
        let answer = reloaded(reload).await;
        let _ = wr.write_all(answer.as_bytes()).await;
        return;
    }
    let request = match line.and_then(|l| Request::parse(l.trim_end_matches('\r'))) {
        Ok(r) => r,
        Err(why) => {
            debug!("control socket: bad request: {why}");
            let _ = wr.write_all(format!("error: {why}\n").as_bytes()).await;
            return;
        }
    };
    let sub = match hub.subscribe(request.clone()) {
        Ok(s) => s,
        Err(why) => {
            let _ = wr.write_all(format!("error: {why}\n").as_bytes()).await;
            return;
        }
    };
    info!("capture started: {request}");
    let mut run = Run {
        sub,
        request,
        packets: 0,
        written: vec![0; hub.interfaces().len()],
        start_us: unix_us(Instant::now()),
    };
    let why = run.stream(&mut rd, &mut wr, &hub).await;
    let dropped: u64 = run.sub.dropped().iter().sum();
    info!(packets = run.packets, dropped, "capture ended ({why})");
}

/// What a reload asked for over the socket is told: `ok` or `refused`, then what the
/// log says of it.
async fn reloaded(reload: Option<ReloadHandle>) -> String {
    let Some(handle) = reload else {
        return "error: this gateway does not reload (it runs without a configuration file)\n"
            .into();
    };
    match handle.reload().await {
        None => "error: the gateway is stopping\n".into(),
        Some(answer) => {
            let head = if answer.outcome.taken() {
                "ok"
            } else {
                "refused"
            };
            format!("{head}\n{}\n", answer.lines().join("\n"))
        }
    }
}

struct Run {
    sub: Subscription,
    request: Request,
    packets: u64,
    /// Packets written, by interface.
    written: Vec<u64>,
    start_us: u64,
}

impl Run {
    /// Streams the capture to `wr`; returns why it ended.
    async fn stream(
        &mut self,
        rd: &mut tokio::net::unix::OwnedReadHalf,
        wr: &mut tokio::net::unix::OwnedWriteHalf,
        hub: &Hub,
    ) -> &'static str {
        let mut head = pcapng::section_header(&format!("mbgate {}", env!("CARGO_PKG_VERSION")));
        for i in hub.interfaces() {
            head.extend(pcapng::interface(&i.name, &i.description));
        }
        let mut out = b"ok\n".to_vec();
        message(&mut out, DATA, &head);
        if wr.write_all(&out).await.is_err() {
            return "the client went away";
        }
        let until = self
            .request
            .seconds
            .map(|s| Instant::now() + Duration::from_secs(s));
        let mut cmd = [0u8; 64];
        let why = loop {
            let mut blocks = Vec::new();
            tokio::select! {
                p = self.sub.rx.recv() => match p {
                    None => break "the gateway stopped",
                    Some(p) => {
                        let mut next = Some(p);
                        // Whatever else is waiting goes in the same message.
                        while let Some(p) = next {
                            self.written[usize::from(p.iface)] += 1;
                            self.packets += 1;
                            blocks.extend(p.block(u32::from(p.iface)));
                            if self.request.count.is_some_and(|n| self.packets >= n) {
                                break;
                            }
                            next = self.sub.rx.try_recv().ok();
                        }
                    }
                },
                r = rd.read(&mut cmd) => match r {
                    Ok(0) | Err(_) => return "the client went away",
                    // `stop`, or anything else: the client wants no more.
                    Ok(_) => break "stopped",
                },
                _ = async { tokio::time::sleep_until(until.expect("guarded")).await }, if until.is_some() => {
                    break "seconds";
                }
            }
            // A gateway that stops ends the capture when its last packet (the drain's
            // answers included) has gone out: the hub closes, `recv` gives `None`.
            let mut msg = Vec::with_capacity(blocks.len() + 5);
            message(&mut msg, DATA, &blocks);
            if wr.write_all(&msg).await.is_err() {
                return "the client went away";
            }
            if self.request.count.is_some_and(|n| self.packets >= n) {
                break "count";
            }
        };
        let end_us = unix_us(Instant::now());
        let dropped = self.sub.dropped();
        let mut tail = Vec::new();
        for (i, (&received, &dropped)) in self.written.iter().zip(&dropped).enumerate() {
            tail.extend(pcapng::statistics(&pcapng::Statistics {
                interface: i as u32,
                start_us: self.start_us,
                end_us,
                received,
                dropped,
            }));
        }
        let total: u64 = dropped.iter().sum();
        let mut msg = Vec::new();
        message(&mut msg, DATA, &tail);
        let end = format!(
            "packets={} dropped={total} why={}",
            self.packets,
            why.replace(' ', "_")
        );
        message(&mut msg, END, end.as_bytes());
        let _ = tokio::time::timeout(Duration::from_secs(5), wr.write_all(&msg)).await;
        why
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reload::{Answer, Outcome};

    /// `reload` is answered `ok` or `refused`, then the lines the log says (the
    /// certificates last); `error:` from a gateway that does not reload.
    #[tokio::test]
    async fn a_reload_is_answered_with_what_the_log_says() {
        assert_eq!(
            reloaded(None).await,
            "error: this gateway does not reload (it runs without a configuration file)\n"
        );
        for (outcome, head) in [
            (
                Outcome::Done {
                    applied: vec!["log.level = \"debug\"".into()],
                    restart: vec![],
                },
                "ok\nreloaded: log.level = \"debug\"\nlisten[0].tls: read again\n",
            ),
            (
                Outcome::Refused("mbgate.toml:1:1: bogus: unknown key".into()),
                "refused\nreload refused: mbgate.toml:1:1: bogus: unknown key; the running configuration stays\nlisten[0].tls: read again\n",
            ),
        ] {
            let (handle, mut asked) = ReloadHandle::new();
            tokio::spawn(async move {
                let a = asked.recv().await.unwrap();
                let certificates = vec!["listen[0].tls: read again".into()];
                a.send(Answer { outcome, certificates }).unwrap();
            });
            assert_eq!(reloaded(Some(handle)).await, head);
        }
    }

    #[tokio::test]
    async fn the_socket_is_made_0660_a_live_one_is_kept_and_a_file_never_replaced() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("control.sock");
        let c = bind(&path).unwrap();
        let mode = std::fs::metadata(&path).unwrap().permissions().mode();
        assert_eq!(mode & 0o777, 0o660);
        assert!(matches!(bind(&path), Err(BindError::InUse(_))));
        drop(c);
        assert!(!path.exists(), "removed when dropped");
        // Left behind by a gateway that stopped: replaced.
        let stale = std::os::unix::net::UnixListener::bind(&path).unwrap();
        drop(stale);
        let c = bind(&path).unwrap();
        drop(c);
        let file = dir.path().join("notes.txt");
        std::fs::write(&file, "keep me").unwrap();
        let e = bind(&file).err().unwrap().to_string();
        assert!(e.contains("it exists and is not a socket"), "{e}");
        assert_eq!(std::fs::read_to_string(&file).unwrap(), "keep me");
    }
}
