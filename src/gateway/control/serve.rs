//! The gateway's end of the control socket (the protocol: `control/mod.rs`): the
//! socket made 0660 in a directory only the gateway may write, who may use it (checked
//! again on each connection by the peer's credentials), one client's request read
//! within a deadline, then a capture streamed from the hub or a reload asked of the
//! gateway and its answer written, every write within a deadline too. Each client
//! holds a slot (waiting for its request, or capturing) that a guard gives back
//! however its task ends.

use super::stream::CaptureRun;
use super::{own_ids, RELOAD, STATUS};
use crate::gateway::reload::ReloadHandle;
use crate::ops::capture::hub::{unix_us, Hub};
use crate::ops::capture::request::{CaptureRequest, MAX_LINE};
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
/// Clients connected that have not yet sent their request (a reload is answered
/// within this slot too); one more is refused with a message. Apart from the
/// captures: eight captures running never keep `mbgate reload` out.
const MAX_WAITING: usize = 16;
/// Clients being told they were refused, at most; past it they are closed at once.
const MAX_REFUSING: usize = 32;
/// A client has this long to send its request (`mbgate capture` sends it at once).
const REQUEST_WITHIN: Duration = Duration::from_secs(2);
/// A write to a client that does not read it within this long ends that client (a
/// capture that stops being read is ended, its slot given back).
const WRITE_WITHIN: Duration = Duration::from_secs(5);
/// The longest a reload is waited for.
const RELOAD_WITHIN: Duration = Duration::from_secs(30);

/// Slots of one kind: a [`TaskSlot`] taken while one is free, given back when dropped.
#[derive(Debug)]
struct TaskSlots {
    taken: AtomicUsize,
    max: usize,
}

/// A slot taken; dropping it (the task ending, by any path, a panic included) gives it
/// back.
#[derive(Debug)]
struct TaskSlot(Arc<TaskSlots>);

impl TaskSlots {
    fn new(max: usize) -> Arc<TaskSlots> {
        Arc::new(TaskSlots {
            taken: AtomicUsize::new(0),
            max,
        })
    }

    fn take(self: &Arc<Self>) -> Option<TaskSlot> {
        self.taken
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                (n < self.max).then_some(n + 1)
            })
            .ok()
            .map(|_| TaskSlot(self.clone()))
    }

    fn taken(&self) -> usize {
        self.taken.load(Ordering::Acquire)
    }
}

impl Drop for TaskSlot {
    fn drop(&mut self) {
        self.0.taken.fetch_sub(1, Ordering::AcqRel);
    }
}

/// Why the control socket could not be made.
#[derive(Debug, thiserror::Error)]
pub(crate) enum BindError {
    #[error("{0} is in use by another running mbgate (give each its own control.socket)")]
    InUse(PathBuf),
    #[error("control socket {path}: refused: {why}")]
    Unsafe { path: PathBuf, why: NotOurs },
    #[error("cannot make the control socket {path}: {error}")]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
}

/// The socket, bound: removed again when dropped.
pub(crate) struct ControlSocket {
    listener: UnixListener,
    path: PathBuf,
}

/// Binds the control socket at `path`, mode 0660. The socket is made under a
/// temporary name, given its mode, then renamed into place, so it is never
/// reachable with a looser mode. A socket left there by a gateway that stopped is
/// replaced; one a running gateway answers on is not.
pub(crate) fn bind(path: &Path) -> Result<ControlSocket, BindError> {
    let io = |error| BindError::Io {
        path: path.to_owned(),
        error,
    };
    if let Err(why) = directory_is_ours(path) {
        return Err(BindError::Unsafe {
            path: path.to_owned(),
            why,
        });
    }
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
    Ok(ControlSocket {
        listener,
        path: path.to_owned(),
    })
}

/// Why the control socket's directory is not one only the gateway may write.
#[derive(Debug, thiserror::Error)]
pub(crate) enum NotOurs {
    #[error("its directory {}: {source}", dir.display())]
    Unreadable {
        dir: PathBuf,
        source: std::io::Error,
    },
    #[error("its directory {} is writable by {} (mode {mode:04o}): another user could put a socket of their own there; use a directory only the gateway's user may write (mode 0755 or 0750, like systemd's RuntimeDirectory)", dir.display(), if mode & 0o002 != 0 { "everyone" } else { "its group" })]
    Writable { dir: PathBuf, mode: u32 },
    #[error("its directory {} belongs to user {owner}, not to the gateway's user ({uid}) or root", dir.display())]
    Owner { dir: PathBuf, owner: u32, uid: u32 },
}

/// Is the directory of `path` one only the gateway may write: its own (or root's,
/// for a gateway run as root), not writable by its group or others? Elsewhere another
/// user could put a socket of their own at the path before the gateway starts, or
/// replace the gateway's after, and `mbgate reload` run by root would talk to it.
fn directory_is_ours(path: &Path) -> Result<(), NotOurs> {
    use std::os::unix::fs::MetadataExt;
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let m = std::fs::metadata(dir).map_err(|source| NotOurs::Unreadable {
        dir: dir.to_owned(),
        source,
    })?;
    let (uid, _) = own_ids();
    let mode = m.mode() & 0o7777;
    if mode & 0o022 != 0 {
        return Err(NotOurs::Writable {
            dir: dir.to_owned(),
            mode,
        });
    }
    if m.uid() != uid && m.uid() != 0 {
        return Err(NotOurs::Owner {
            dir: dir.to_owned(),
            owner: m.uid(),
            uid,
        });
    }
    Ok(())
}

impl Drop for ControlSocket {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

/// Serves captures on `control` until `shutdown`; the socket is removed then.
pub(crate) async fn serve(
    control: ControlSocket,
    asked: ControlServed,
    shutdown: CancellationToken,
) {
    info!(
        "control socket {} (mbgate capture, mbgate reload, mbgate status)",
        control.path.display()
    );
    let waiting = TaskSlots::new(MAX_WAITING);
    let captures = TaskSlots::new(MAX_CLIENTS);
    let refusing = TaskSlots::new(MAX_REFUSING);
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
        let refusal = match allowed(&stream) {
            Err(why) => {
                warn!("control socket: {why}; refused");
                Some(why)
            }
            Ok(()) => None,
        };
        let slot = match refusal {
            None => waiting.take(),
            Some(_) => None,
        };
        let Some(slot) = slot else {
            let why = refusal.unwrap_or(ControlRefusal::Busy);
            // Told in a task of its own (at most MAX_REFUSING at once): the accept
            // loop never waits on a client.
            if let Some(r) = refusing.take() {
                tokio::spawn(async move {
                    refuse(stream, &why).await;
                    drop(r);
                });
            }
            continue;
        };
        tokio::spawn(client(stream, asked.clone(), slot, captures.clone()));
    }
    drop(control);
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

/// Why a client of the control socket is refused, or its request.
#[derive(Debug, thiserror::Error)]
enum ControlRefusal {
    #[error("cannot tell who connected ({0})")]
    Who(std::io::Error),
    #[error("user {peer_uid} may not use the control socket: root, or the gateway's user ({uid}) or group ({gid}) only")]
    Stranger { peer_uid: u32, uid: u32, gid: u32 },
    #[error("{MAX_WAITING} clients are waiting to be served already")]
    Busy,
    #[error("{0}")]
    Read(std::io::Error),
    #[error("closed before its request")]
    Closed,
    #[error("a request longer than {MAX_LINE} bytes")]
    TooLong,
    #[error("no request within {} s", REQUEST_WITHIN.as_secs())]
    Slow,
    #[error("a request that is not text")]
    NotText,
    #[error(transparent)]
    Request(#[from] crate::ops::capture::request::BadRequest),
}

/// May the peer capture? Root, the gateway's own user, or its group (primary or
/// supplementary). The file's mode lets only those connect; this holds even if the
/// mode was loosened by hand.
fn allowed(stream: &UnixStream) -> Result<(), ControlRefusal> {
    let cred = stream.peer_cred().map_err(ControlRefusal::Who)?;
    let (uid, gid) = own_ids();
    let (peer_uid, peer_gid) = (cred.uid(), cred.gid());
    if peer_uid == 0 || peer_uid == uid || peer_gid == gid || groups_of(cred.pid()).contains(&gid) {
        return Ok(());
    }
    Err(ControlRefusal::Stranger { peer_uid, uid, gid })
}

/// Tells a client it is refused: reads what it sent first (within a moment), so that
/// closing does not reset the connection and lose the answer, then writes `error: why`.
async fn refuse(stream: UnixStream, why: &ControlRefusal) {
    let (mut rd, mut wr) = stream.into_split();
    let _ = tokio::time::timeout(Duration::from_millis(500), request_line(&mut rd)).await;
    let _ = tokio::time::timeout(
        WRITE_WITHIN,
        wr.write_all(format!("error: {why}\n").as_bytes()),
    )
    .await;
}

/// Writes `bytes` to a client that has [`WRITE_WITHIN`] to take them.
pub(super) async fn write_within(
    wr: &mut tokio::net::unix::OwnedWriteHalf,
    bytes: &[u8],
) -> Result<(), &'static str> {
    match tokio::time::timeout(WRITE_WITHIN, wr.write_all(bytes)).await {
        Ok(Ok(())) => Ok(()),
        Ok(Err(_)) => Err("the client went away"),
        Err(_) => Err("the client stopped reading"),
    }
}

/// Reads the request line: at most [`MAX_LINE`] bytes, within [`REQUEST_WITHIN`].
async fn request_line(rd: &mut tokio::net::unix::OwnedReadHalf) -> Result<String, ControlRefusal> {
    let mut line = Vec::new();
    let read = async {
        let mut byte = [0u8; 256];
        loop {
            let n = rd.read(&mut byte).await.map_err(ControlRefusal::Read)?;
            if n == 0 {
                return Err(ControlRefusal::Closed);
            }
            line.extend_from_slice(&byte[..n]);
            if let Some(end) = line.iter().position(|&b| b == b'\n') {
                line.truncate(end);
                return Ok(());
            }
            if line.len() > MAX_LINE {
                return Err(ControlRefusal::TooLong);
            }
        }
    };
    match tokio::time::timeout(REQUEST_WITHIN, read).await {
        Err(_) => return Err(ControlRefusal::Slow),
        Ok(r) => r?,
    }
    String::from_utf8(line).map_err(|_| ControlRefusal::NotText)
}

/// What the socket's clients ask of: the capture's hub, the reload (none: the gateway
/// has no file to read again), the numbers a status is made of.
#[derive(Clone)]
pub(crate) struct ControlServed {
    pub(crate) hub: Hub,
    pub(crate) reload: Option<ReloadHandle>,
    pub(crate) board: Arc<crate::ops::metrics::Board>,
}

/// One client, holding `waiting` until its request is read: a reload, a status, or a
/// capture (its request, then packets until a stop condition) in one of `captures`.
async fn client(
    stream: UnixStream,
    asked: ControlServed,
    waiting: TaskSlot,
    captures: Arc<TaskSlots>,
) {
    let ControlServed { hub, reload, board } = asked;
    let (mut rd, mut wr) = stream.into_split();
    let line = request_line(&mut rd).await;
    if let Ok(l) = &line {
        if let Some(answer) = answer(l.trim_end_matches('\r'), reload, board).await {
            let _ = write_within(&mut wr, answer.as_bytes()).await;
            return;
        }
    }
    let request = match line.and_then(|l| Ok(CaptureRequest::parse(l.trim_end_matches('\r'))?)) {
        Ok(r) => r,
        Err(why) => {
            debug!("control socket: bad request: {why}");
            let _ = write_within(&mut wr, format!("error: {why}\n").as_bytes()).await;
            return;
        }
    };
    let Some(slot) = captures.take() else {
        let why = format!("error: {MAX_CLIENTS} captures are running already\n");
        let _ = write_within(&mut wr, why.as_bytes()).await;
        return;
    };
    drop(waiting);
    debug!(
        captures = captures.taken(),
        "control socket: a capture begins"
    );
    let sub = match hub.subscribe(request.clone()) {
        Ok(s) => s,
        Err(why) => {
            let _ = write_within(&mut wr, format!("error: {why}\n").as_bytes()).await;
            return;
        }
    };
    info!("capture started: {request}");
    let mut run = CaptureRun {
        sub,
        request,
        packets: 0,
        written: vec![0; hub.interfaces().len()],
        start_us: unix_us(Instant::now()),
    };
    let why = run.stream(&mut rd, &mut wr, &hub).await;
    let dropped: u64 = run.sub.dropped().iter().sum();
    info!(packets = run.packets, dropped, "capture ended ({why})");
    drop(slot);
}

/// The answer to a status or a reload; none for any other request (a capture).
async fn answer(
    line: &str,
    reload: Option<ReloadHandle>,
    board: Arc<crate::ops::metrics::Board>,
) -> Option<String> {
    if line == STATUS {
        // Rendered beside the runtime's one thread, as the metrics listener renders it
        // on a thread of its own: the lines' loops do not wait for it.
        let text = tokio::task::spawn_blocking(move || crate::ops::metrics::expose::render(&board))
            .await
            .unwrap_or_default();
        return Some(format!("ok\n{text}"));
    }
    if line == RELOAD {
        return Some(
            match tokio::time::timeout(RELOAD_WITHIN, reloaded(reload)).await {
                Ok(a) => a,
                Err(_) => format!(
                    "error: no answer from the gateway's reload within {} s\n",
                    RELOAD_WITHIN.as_secs()
                ),
            },
        );
    }
    None
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

#[cfg(test)]
mod tests {
    use super::super::END;
    use super::*;
    use crate::gateway::reload::{ReloadOutcome, ReloadReport};
    use crate::ops::capture::packet::Packet;

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
                ReloadOutcome::Done {
                    applied: vec!["log.level = \"debug\"".into()],
                    restart: vec![],
                },
                "ok\nreloaded: log.level = \"debug\"\nlisten[0].tls: read again\n",
            ),
            (
                ReloadOutcome::Refused("mbgate.toml:1:1: bogus: unknown key".into()),
                "refused\nreload refused: mbgate.toml:1:1: bogus: unknown key; the running configuration stays\nlisten[0].tls: read again\n",
            ),
        ] {
            let (handle, mut asked) = ReloadHandle::new();
            tokio::spawn(async move {
                let a = asked.recv().await.unwrap();
                let certificates = vec!["listen[0].tls: read again".into()];
                a.send(ReloadReport { outcome, certificates }).unwrap();
            });
            assert_eq!(reloaded(Some(handle)).await, head);
        }
    }

    /// Stopped with more waiting than its channel holds: every packet handed to the
    /// capture before the stop is written, and the ones its full channel dropped are
    /// counted, so the two make up all that was sent; the file's statistics say the
    /// same.
    #[tokio::test]
    async fn a_stop_drains_what_waits_and_counts_what_was_dropped_exactly() {
        use crate::ops::capture::hub::{Interface, PER_SUBSCRIBER};
        use crate::ops::capture::packet::{Dir, Part, Proto};
        use crate::ops::capture::pcapng_read;
        let iface = |n: &str| Interface {
            name: n.into(),
            description: String::new(),
        };
        let (hub, task) = Hub::new(vec![iface("tcp"), iface("/dev/ttyX")]);
        tokio::spawn(task);
        let (gw_end, client_end) = UnixStream::pair().unwrap();
        let request = CaptureRequest::parse("capture").unwrap();
        let mut run = CaptureRun {
            sub: hub.subscribe(request.clone()).unwrap(),
            request,
            packets: 0,
            written: vec![0; 2],
            start_us: unix_us(Instant::now()),
        };
        let server = {
            let hub = hub.clone();
            tokio::spawn(async move {
                let (mut rd, mut wr) = gw_end.into_split();
                let why = run.stream(&mut rd, &mut wr, &hub).await;
                (why, run.packets, run.sub.dropped())
            })
        };
        let (rd, mut wr) = client_end.into_split();
        let mut rd = tokio::io::BufReader::new(rd);
        let mut ok = String::new();
        tokio::io::AsyncBufReadExt::read_line(&mut rd, &mut ok)
            .await
            .unwrap();
        assert_eq!(ok, "ok\n");
        // More than the channel holds, with no await between: the capture takes
        // none of them until the stop is written.
        let sent = PER_SUBSCRIBER + 904;
        let tap = hub.tap(1);
        for i in 0..sent {
            let bytes = vec![1, 3, (i >> 8) as u8, i as u8];
            tap.send(
                Packet::new(Dir::Out, Part::Query, Proto::Mbrtu, bytes),
                Instant::now(),
            );
        }
        wr.write_all(b"stop\n").await.unwrap();
        let mut file = Vec::new();
        let end = loop {
            let mut head = [0u8; 5];
            rd.read_exact(&mut head).await.unwrap();
            let len = u32::from_be_bytes([head[1], head[2], head[3], head[4]]) as usize;
            let mut payload = vec![0u8; len];
            rd.read_exact(&mut payload).await.unwrap();
            if head[0] == END {
                break String::from_utf8(payload).unwrap();
            }
            file.extend(payload);
        };
        let (why, packets, dropped) = server.await.unwrap();
        assert_eq!(why, "stopped");
        assert_eq!(dropped, vec![0, 904]);
        assert_eq!(packets as usize, PER_SUBSCRIBER);
        assert_eq!(
            end,
            format!("packets={PER_SUBSCRIBER} dropped=904 why=stopped")
        );
        let read = pcapng_read::read(&file).unwrap();
        assert_eq!((read.packets.len(), read.damage), (PER_SUBSCRIBER, None));
        // The first packet handed on is the file's first: nothing before the
        // channel filled was lost.
        let first = pcapng_read::exported(read.packets[0].data).unwrap();
        assert_eq!(first.payload, [1, 3, 0, 0]);
    }

    /// A reload the gateway never answers is given up after its 30 s: the client is
    /// told so and its slot given back (the clock paused, so the test takes no 30 s).
    #[tokio::test(start_paused = true)]
    async fn a_reload_never_answered_is_given_up_after_its_time() {
        let (hub, task) = Hub::new(Vec::new());
        tokio::spawn(task);
        let (handle, _never_answered) = ReloadHandle::new();
        let (gw_end, mut client_end) = UnixStream::pair().unwrap();
        client_end.write_all(b"reload\n").await.unwrap();
        let waiting = TaskSlots::new(1);
        let slot = waiting.take().unwrap();
        let started = Instant::now();
        let asked = ControlServed {
            hub,
            reload: Some(handle),
            board: Arc::default(),
        };
        let served = tokio::spawn(client(gw_end, asked, slot, TaskSlots::new(1)));
        let mut answer = String::new();
        client_end.read_to_string(&mut answer).await.unwrap();
        assert_eq!(
            answer,
            "error: no answer from the gateway's reload within 30 s\n"
        );
        assert!(started.elapsed() >= RELOAD_WITHIN);
        served.await.unwrap();
        assert_eq!(waiting.taken(), 0);
    }

    /// A slot is given back however its holder ends: dropped, or its task panicking.
    #[tokio::test]
    async fn slots_are_given_back_on_every_path() {
        let slots = TaskSlots::new(2);
        let a = slots.take().unwrap();
        let b = slots.take().unwrap();
        assert!(slots.take().is_none());
        drop(a);
        let c = slots.take().unwrap();
        let task = tokio::spawn(async move {
            let _held = b;
            panic!("a client's task fails");
        });
        assert!(task.await.is_err());
        assert_eq!(slots.taken(), 1);
        drop(c);
        assert_eq!(slots.taken(), 0);
    }

    /// The socket's directory: not one others may write, and the gateway's own.
    #[tokio::test]
    async fn a_directory_others_may_write_is_refused_saying_why() {
        let dir = tempfile::tempdir().unwrap();
        for (mode, says) in [
            (0o1777, "writable by everyone (mode 1777)"),
            (0o770, "writable by its group (mode 0770)"),
        ] {
            std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(mode)).unwrap();
            let e = bind(&dir.path().join("control.sock"))
                .err()
                .unwrap()
                .to_string();
            assert!(e.contains(says), "{e}");
            assert!(!dir.path().join("control.sock").exists());
        }
        std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o750)).unwrap();
        drop(bind(&dir.path().join("control.sock")).unwrap());
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
