//! A descriptor of our own, non-blocking, on tokio's reactor (`ReactorFd`), and the
//! reads and writes straight to a descriptor: the one place where the line's port
//! (`serial/stream.rs`), the precise timer (`serial/timer.rs`) and the virtual wire's
//! ptys (`wire/pty.rs`) register a descriptor with `AsyncFd` and call `read(2)` and
//! `write(2)` on it, each unsafe block argued once here.
//!
//! Safe to call from anywhere: what each block needs of the descriptor is carried by
//! the types (an `OwnedFd` given up to the registration; a `BorrowedFd` for a read
//! or write), never by the caller's word.

use std::io;
use std::os::fd::{AsFd, AsRawFd, BorrowedFd, OwnedFd, RawFd};
use std::task::{Context, Poll};
use tokio::io::unix::{AsyncFd, AsyncFdReadyGuard};
use tokio::io::Interest;

/// A descriptor owned here, set non-blocking and registered on the current runtime's
/// reactor for the readiness asked for; closed (after its registration is removed)
/// when this drops.
#[derive(Debug)]
pub(crate) struct ReactorFd(AsyncFd<OwnedFd>);

impl ReactorFd {
    /// Takes `fd`, sets it non-blocking and registers it for `interest`. Must be
    /// called on a tokio runtime (tokio panics otherwise).
    pub(crate) fn new(fd: OwnedFd, interest: Interest) -> io::Result<ReactorFd> {
        set_nonblocking(fd.as_fd())?;
        // SAFETY: `AsyncFd::register_with_interest` needs the descriptor to stay open,
        // and the same, for as long as the `AsyncFd` holds it. An `OwnedFd` closes its
        // descriptor only when it drops, which is when the `AsyncFd` holding it does,
        // and its `as_raw_fd` always answers the one descriptor it owns; nothing else
        // owns it (`OwnedFd`'s own contract), so nothing else closes it meanwhile.
        #[allow(unsafe_code)]
        let fd = unsafe { AsyncFd::register_with_interest(fd, interest) }?;
        Ok(ReactorFd(fd))
    }

    /// A duplicate of this descriptor (`dup`, close-on-exec; the same open file, so
    /// the same non-blocking flag), registered on its own for `interest`: a second
    /// registration of one file, for a readiness the first was not asked for.
    pub(crate) fn duplicate(&self, interest: Interest) -> io::Result<ReactorFd> {
        ReactorFd::new(self.as_fd().try_clone_to_owned()?, interest)
    }

    /// Waits until the reactor says it is readable (registered for reading).
    pub(crate) async fn readable(&self) -> io::Result<AsyncFdReadyGuard<'_, OwnedFd>> {
        self.0.readable().await
    }

    /// Polls for the reactor's readability (registered for reading).
    pub(crate) fn poll_read_ready<'a>(
        &'a self,
        cx: &mut Context<'_>,
    ) -> Poll<io::Result<AsyncFdReadyGuard<'a, OwnedFd>>> {
        self.0.poll_read_ready(cx)
    }

    /// Polls for the reactor's writability (registered for writing).
    pub(crate) fn poll_write_ready<'a>(
        &'a self,
        cx: &mut Context<'_>,
    ) -> Poll<io::Result<AsyncFdReadyGuard<'a, OwnedFd>>> {
        self.0.poll_write_ready(cx)
    }

    /// Reads what is there, without waiting: `WouldBlock` when nothing is.
    pub(crate) fn read(&self, buf: &mut [u8]) -> io::Result<usize> {
        read(self.as_fd(), buf)
    }

    /// Writes what the descriptor takes, without waiting: `WouldBlock` when it has no
    /// room.
    pub(crate) fn write(&self, buf: &[u8]) -> io::Result<usize> {
        write(self.as_fd(), buf)
    }
}

impl AsFd for ReactorFd {
    fn as_fd(&self) -> BorrowedFd<'_> {
        self.0.get_ref().as_fd()
    }
}

impl AsRawFd for ReactorFd {
    fn as_raw_fd(&self) -> RawFd {
        self.0.get_ref().as_raw_fd()
    }
}

/// Sets `O_NONBLOCK` on the open file `fd` names, keeping its other status flags.
fn set_nonblocking(fd: BorrowedFd<'_>) -> io::Result<()> {
    let fd = fd.as_raw_fd();
    // SAFETY: F_GETFL and F_SETFL take and give integers only, no pointers; `fd` is
    // open for the call (borrowed from its owner).
    #[allow(unsafe_code)]
    let r = unsafe {
        let flags = libc::fcntl(fd, libc::F_GETFL);
        if flags < 0 {
            -1
        } else {
            libc::fcntl(fd, libc::F_SETFL, flags | libc::O_NONBLOCK)
        }
    };
    if r < 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(())
}

/// One `read(2)` into `buf`: how many bytes came (0 at end of file), or the error
/// (`WouldBlock` on a non-blocking descriptor with nothing to read).
pub(crate) fn read(fd: BorrowedFd<'_>, buf: &mut [u8]) -> io::Result<usize> {
    // SAFETY: `buf` is valid for writes of `buf.len()` bytes, and borrowed mutably,
    // so nothing else reads or writes it during the call; `fd` is open for the call.
    #[allow(unsafe_code)]
    let n = unsafe { libc::read(fd.as_raw_fd(), buf.as_mut_ptr().cast(), buf.len()) };
    if n < 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(n as usize)
}

/// One `write(2)` of `buf`: how many bytes the descriptor took, or the error
/// (`WouldBlock` on a non-blocking descriptor with no room).
pub(crate) fn write(fd: BorrowedFd<'_>, buf: &[u8]) -> io::Result<usize> {
    // SAFETY: `buf` is valid for reads of `buf.len()` bytes for the call; `fd` is
    // open for the call.
    #[allow(unsafe_code)]
    let n = unsafe { libc::write(fd.as_raw_fd(), buf.as_ptr().cast(), buf.len()) };
    if n < 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(n as usize)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    /// A pipe's two ends, as std makes them (blocking, close-on-exec).
    fn pipe() -> (OwnedFd, OwnedFd) {
        let (r, w) = std::io::pipe().unwrap();
        (OwnedFd::from(r), OwnedFd::from(w))
    }

    /// The read end is made non-blocking (an empty pipe says `WouldBlock` instead of
    /// hanging), its readiness waits for bytes and comes with them, and the bytes
    /// read are those written, in order.
    #[tokio::test]
    async fn a_read_end_waits_for_bytes_and_never_blocks() {
        let (r, w) = pipe();
        let r = std::sync::Arc::new(ReactorFd::new(r, Interest::READABLE).unwrap());
        // On a thread, so that a read that blocks fails the test instead of hanging it.
        let (tx, rx) = std::sync::mpsc::channel();
        let reader = r.clone();
        std::thread::spawn(move || tx.send(reader.read(&mut [0u8; 8]).map_err(|e| e.kind())));
        let first = rx.recv_timeout(Duration::from_secs(5));
        assert_eq!(
            first,
            Ok(Err(io::ErrorKind::WouldBlock)),
            "the read blocked"
        );
        let mut buf = [0u8; 8];

        let waiting = {
            let r = r.clone();
            tokio::spawn(async move {
                let mut ready = r.readable().await.unwrap();
                let mut buf = [0u8; 8];
                let n = r.read(&mut buf).unwrap();
                ready.clear_ready();
                buf[..n].to_vec()
            })
        };
        tokio::time::sleep(Duration::from_millis(100)).await;
        assert!(
            !waiting.is_finished(),
            "readable before any byte was written"
        );
        assert_eq!(write(w.as_fd(), b"abc").unwrap(), 3);
        assert_eq!(waiting.await.unwrap(), b"abc");

        // The writer gone, the reader reads the end of file (0), not an error.
        drop(w);
        assert_eq!(r.read(&mut buf).unwrap(), 0);
    }

    /// A write end with no room says `WouldBlock` (it is non-blocking); a duplicate
    /// registered for writing is woken once the far end reads, and the write then
    /// goes through; the duplicate shares the original's open file and its flag.
    #[tokio::test]
    async fn a_full_write_end_waits_on_a_duplicate_for_room() {
        let (r, w) = pipe();
        // Registered for reading only, as the serial port's writer is
        // (`serial/stream.rs`): writes go straight to it.
        let w = std::sync::Arc::new(ReactorFd::new(w, Interest::READABLE).unwrap());
        // Filled on a thread, so that a write that blocks fails the test instead of
        // hanging it.
        let (tx, rx) = std::sync::mpsc::channel();
        let filler = w.clone();
        std::thread::spawn(move || {
            let chunk = [7u8; 4096];
            let mut written = 0usize;
            let full = loop {
                match filler.write(&chunk) {
                    Ok(n) => written += n,
                    Err(e) => break e.kind(),
                }
                assert!(written < 16 << 20, "a pipe that never fills");
            };
            tx.send((written, full))
        });
        let (written, full) = rx
            .recv_timeout(Duration::from_secs(10))
            .expect("the write blocked");
        assert_eq!(full, io::ErrorKind::WouldBlock);

        let dup = w.duplicate(Interest::WRITABLE).unwrap();
        assert_ne!(dup.as_raw_fd(), w.as_raw_fd());
        assert_eq!(
            dup.write(b"x").unwrap_err().kind(),
            io::ErrorKind::WouldBlock
        );
        let drain = std::thread::spawn(move || {
            // Blocking reads on std's end: all that was written, then the one byte.
            let mut buf = vec![0u8; 65536];
            let mut got = 0usize;
            while got < written + 1 {
                got += read(r.as_fd(), &mut buf).unwrap();
            }
            got
        });
        let took = tokio::time::timeout(Duration::from_secs(10), async {
            loop {
                let mut ready = std::future::poll_fn(|cx| dup.poll_write_ready(cx))
                    .await
                    .unwrap();
                match ready.try_io(|_| dup.write(b"x")) {
                    Ok(r) => break r,
                    Err(_would_block) => continue,
                }
            }
        })
        .await
        .expect("woken once the far end read")
        .unwrap();
        assert_eq!(took, 1);
        assert_eq!(drain.join().unwrap(), written + 1);
    }
}
