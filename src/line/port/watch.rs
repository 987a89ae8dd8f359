//! Waiting for a missing port to come back: an inotify watch on the directory where the
//! first missing part of its path will appear (the node, a by-id link, the link's own
//! directory), so a USB adapter plugged back in is reopened as soon as its node or link
//! is there, not at the next attempt of the backoff (docs/raspberry-pi.md "When the
//! adapter is pulled out"). One descriptor and one watch while the port is closed,
//! none while it is open; no timer, and no wake while nothing changes in that directory.

use crate::line::port::fd::ReactorFd;
use std::ffi::{CString, OsString};
use std::io;
use std::os::fd::{FromRawFd, OwnedFd};
use std::os::unix::ffi::OsStrExt;
use std::path::{Component, Path, PathBuf};
use std::task::{Context, Poll};
use tokio::io::Interest;

/// Where a path waits: a directory, and the name in it whose change may make the path
/// open.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct AwaitedPart {
    pub(crate) dir: PathBuf,
    pub(crate) name: OsString,
}

/// Where `path` waits for something to change, following symbolic links as an open
/// does: the first part that does not exist (the node; a by-id link; `by-id` itself,
/// which udev removes with its last link), in the directory that would hold it. When
/// every part exists, the node itself, in its directory: its mode and owner may still
/// change (udev sets them after the kernel has made the node). `None` for a path that
/// loops through links.
pub(crate) fn awaited(path: &Path) -> Option<AwaitedPart> {
    let mut todo: Vec<OsString> = Vec::new();
    let mut at = if path.is_absolute() {
        PathBuf::from("/")
    } else {
        std::env::current_dir().ok()?
    };
    push_front(&mut todo, path);
    let mut last = None;
    let mut hops = 0;
    while let Some(part) = todo.pop() {
        match part.as_bytes() {
            b"/" => at = PathBuf::from("/"),
            b"." => {}
            b".." => {
                at.pop();
            }
            _ => {
                let next = at.join(&part);
                let Ok(meta) = std::fs::symlink_metadata(&next) else {
                    return Some(AwaitedPart {
                        dir: at,
                        name: part,
                    });
                };
                if meta.file_type().is_symlink() {
                    hops += 1;
                    if hops > 40 {
                        return None;
                    }
                    let target = std::fs::read_link(&next).ok()?;
                    push_front(&mut todo, &target);
                } else {
                    last = Some(AwaitedPart {
                        dir: at.clone(),
                        name: part,
                    });
                    at = next;
                }
            }
        }
    }
    last
}

/// Puts the parts of `path` before those of `todo` (a stack: its last is next).
fn push_front(todo: &mut Vec<OsString>, path: &Path) {
    for c in path.components().rev() {
        todo.push(match c {
            Component::RootDir => OsString::from("/"),
            Component::CurDir => OsString::from("."),
            Component::ParentDir => OsString::from(".."),
            Component::Normal(n) => n.to_owned(),
            Component::Prefix(p) => p.as_os_str().to_owned(),
        });
    }
}

/// What a change of the watched directory may have done for the port.
const MASK: u32 = libc::IN_CREATE
    | libc::IN_MOVED_TO
    | libc::IN_ATTRIB
    | libc::IN_DELETE_SELF
    | libc::IN_MOVE_SELF
    | libc::IN_ONLYDIR;

/// The header of one `struct inotify_event` (inotify(7)): wd, mask, cookie, len; then
/// `len` bytes of name, padded with NULs.
const EVENT_HEADER: usize = 16;

/// A watch for a port's path to come back (the module notes).
#[derive(Debug)]
pub(crate) struct NodeWatch {
    path: PathBuf,
    /// The inotify instance, on the reactor; made afresh when the place moves.
    fd: ReactorFd,
    watching: AwaitedPart,
    /// Something changed that the loop has not been told of yet.
    changed: bool,
    buf: Box<[u8]>,
}

impl NodeWatch {
    /// A watch for `path`; `None` where none can be made (no inotify, a path that loops,
    /// no directory to watch), and then the backoff's attempts are all there is. Must be
    /// called on a tokio runtime.
    pub(crate) fn new(path: &Path) -> Option<NodeWatch> {
        Self::armed(path, awaited(path)?)
    }

    /// A watch on where `path` was found to wait (`watching`), which may have moved
    /// since it was found.
    fn armed(path: &Path, watching: AwaitedPart) -> Option<NodeWatch> {
        let fd = arm(&watching)
            .inspect_err(|e| {
                tracing::debug!(path = %path.display(), dir = %watching.dir.display(), "no inotify watch: {e}")
            })
            .ok()?;
        said_watching(path, &watching);
        let mut w = NodeWatch {
            path: path.to_owned(),
            fd,
            watching,
            changed: false,
            buf: vec![0u8; 4096].into_boxed_slice(),
        };
        w.check_after_arming();
        Some(w)
    }

    /// After an open that failed: watches where the path waits now, if that moved
    /// (a directory appeared, a link now points elsewhere).
    pub(crate) fn rearm(&mut self) {
        let Some(now) = awaited(&self.path) else {
            return;
        };
        if now == self.watching {
            return;
        }
        match arm(&now) {
            Ok(fd) => {
                said_watching(&self.path, &now);
                self.fd = fd;
                self.watching = now;
                self.check_after_arming();
            }
            Err(e) => tracing::debug!(dir = %now.dir.display(), "no inotify watch: {e}"),
        }
    }

    /// What was missing may have appeared between the failed open and the watch: if
    /// the path waits elsewhere now, that is a change already.
    fn check_after_arming(&mut self) {
        if awaited(&self.path).as_ref() != Some(&self.watching) {
            self.changed = true;
        }
    }

    /// Ready once something changed where the path waits (the awaited name made, moved
    /// in, its mode or owner set; the directory itself gone; events lost): then an open
    /// may succeed. Cancel-safe: what was read stays here.
    pub(crate) fn poll_changed(&mut self, cx: &mut Context<'_>) -> Poll<()> {
        loop {
            if std::mem::take(&mut self.changed) {
                return Poll::Ready(());
            }
            let mut ready = match self.fd.poll_read_ready(cx) {
                Poll::Ready(Ok(r)) => r,
                // A reactor error: never seen; the backoff's attempts go on.
                Poll::Ready(Err(_)) | Poll::Pending => return Poll::Pending,
            };
            let buf = &mut self.buf;
            match ready.try_io(|fd| crate::line::port::fd::read(std::os::fd::AsFd::as_fd(fd), buf))
            {
                Ok(Ok(n)) => self.changed = relevant(&self.buf[..n], &self.watching.name),
                Ok(Err(_)) => return Poll::Pending,
                Err(_would_block) => continue,
            }
        }
    }
}

/// Where the watch now waits, at debug level: with the attempts' errors, the story of
/// an outage whose port came back later than its node.
fn said_watching(path: &Path, at: &AwaitedPart) {
    tracing::debug!(
        path = %path.display(),
        "watching {} for {:?}",
        at.dir.display(),
        at.name
    );
}

/// Waits until `watch` says something changed; for ever where there is none.
pub(crate) async fn changed(watch: &mut Option<NodeWatch>) {
    match watch {
        Some(w) => std::future::poll_fn(|cx| w.poll_changed(cx)).await,
        None => std::future::pending().await,
    }
}

/// Does this batch of events concern `name`, or the watch itself?
fn relevant(mut events: &[u8], name: &std::ffi::OsStr) -> bool {
    let mut any = false;
    while events.len() >= EVENT_HEADER {
        let word = |i: usize| u32::from_ne_bytes(events[i..i + 4].try_into().unwrap_or([0; 4]));
        let (mask, len) = (word(4), word(12) as usize);
        let end = (EVENT_HEADER + len).min(events.len());
        let raw = &events[EVENT_HEADER..end];
        let this = &raw[..raw.iter().position(|&b| b == 0).unwrap_or(raw.len())];
        let about_the_watch = mask
            & (libc::IN_Q_OVERFLOW | libc::IN_IGNORED | libc::IN_DELETE_SELF | libc::IN_MOVE_SELF)
            != 0;
        any |= about_the_watch || this == name.as_bytes();
        events = &events[end..];
    }
    any
}

/// An inotify instance watching `at.dir`, non-blocking, on the reactor.
fn arm(at: &AwaitedPart) -> io::Result<ReactorFd> {
    // SAFETY: inotify_init1 takes flags only and returns a new descriptor or -1.
    #[allow(unsafe_code)]
    let raw = unsafe { libc::inotify_init1(libc::IN_NONBLOCK | libc::IN_CLOEXEC) };
    if raw < 0 {
        return Err(io::Error::last_os_error());
    }
    // SAFETY: `raw` is the new descriptor, owned by nothing else.
    #[allow(unsafe_code)]
    let fd = unsafe { OwnedFd::from_raw_fd(raw) };
    let dir = CString::new(at.dir.as_os_str().as_bytes())
        .map_err(|_| io::Error::from(io::ErrorKind::InvalidInput))?;
    // SAFETY: `dir` is a NUL-terminated string that lives across the call; `raw` is
    // open (owned by `fd` above).
    #[allow(unsafe_code)]
    let wd = unsafe { libc::inotify_add_watch(raw, dir.as_ptr(), MASK) };
    if wd < 0 {
        return Err(io::Error::last_os_error());
    }
    ReactorFd::new(fd, Interest::READABLE)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::future::poll_fn;
    use std::time::Duration;

    fn at(dir: &Path, name: &str) -> Option<AwaitedPart> {
        Some(AwaitedPart {
            dir: dir.to_owned(),
            name: name.into(),
        })
    }

    /// The first missing part, links followed: a missing directory, a missing link, a
    /// link to a missing node (the node), and a node that is there (itself).
    #[test]
    fn awaited_is_the_first_missing_part_links_followed() {
        let d = tempfile::tempdir().unwrap();
        let root = d.path().canonicalize().unwrap();
        let link = root.join("serial/by-id/usb-FTDI_X-if00-port0");
        assert_eq!(awaited(&link), at(&root, "serial"));
        std::fs::create_dir_all(root.join("serial/by-id")).unwrap();
        assert_eq!(
            awaited(&link),
            at(&root.join("serial/by-id"), "usb-FTDI_X-if00-port0")
        );
        std::os::unix::fs::symlink("../../ttyUSB0", &link).unwrap();
        assert_eq!(awaited(&link), at(&root, "ttyUSB0"));
        std::fs::write(root.join("ttyUSB0"), b"").unwrap();
        assert_eq!(awaited(&link), at(&root, "ttyUSB0"));
        assert_eq!(awaited(&root.join("ttyUSB0")), at(&root, "ttyUSB0"));
        std::os::unix::fs::symlink("loop", root.join("loop")).unwrap();
        assert_eq!(awaited(&root.join("loop")), None);
    }

    async fn changed_within(w: &mut NodeWatch, within: Duration) -> bool {
        tokio::time::timeout(within, poll_fn(|cx| w.poll_changed(cx)))
            .await
            .is_ok()
    }

    /// Wakes for the awaited name only: another file in the directory is no reason to
    /// open; the by-id directory made, then the link in it, then the node's mode set
    /// are each one.
    #[tokio::test]
    async fn wakes_when_the_awaited_part_appears_and_not_for_others() {
        let d = tempfile::tempdir().unwrap();
        let root = d.path().canonicalize().unwrap();
        let link = root.join("by-id/usb-X");
        let mut w = NodeWatch::new(&link).unwrap();
        std::fs::write(root.join("other"), b"").unwrap();
        assert!(!changed_within(&mut w, Duration::from_millis(300)).await);
        std::fs::create_dir(root.join("by-id")).unwrap();
        assert!(changed_within(&mut w, Duration::from_secs(5)).await);
        w.rearm();
        assert_eq!(w.watching, at(&root.join("by-id"), "usb-X").unwrap());
        std::fs::write(root.join("ttyUSB0"), b"").unwrap();
        std::os::unix::fs::symlink("../ttyUSB0", &link).unwrap();
        assert!(changed_within(&mut w, Duration::from_secs(5)).await);
        w.rearm();
        assert_eq!(w.watching, at(&root, "ttyUSB0").unwrap());
        assert!(!changed_within(&mut w, Duration::from_millis(300)).await);
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(root.join("ttyUSB0"), std::fs::Permissions::from_mode(0o660))
            .unwrap();
        assert!(changed_within(&mut w, Duration::from_secs(5)).await);
    }

    /// A part that appears between the failed open and the watch is not missed: the
    /// watch is armed where the path waited, then the path is looked at again.
    #[tokio::test]
    async fn a_change_before_the_watch_counts() {
        let d = tempfile::tempdir().unwrap();
        let root = d.path().canonicalize().unwrap();
        let node = root.join("dir/node");
        let before = awaited(&node).unwrap();
        assert_eq!(before, at(&root, "dir").unwrap());
        std::fs::create_dir(root.join("dir")).unwrap();
        let mut w = NodeWatch::armed(&node, before).unwrap();
        assert!(changed_within(&mut w, Duration::from_millis(100)).await);
        let mut settled = NodeWatch::new(&node).unwrap();
        assert!(!changed_within(&mut settled, Duration::from_millis(300)).await);
    }
}
