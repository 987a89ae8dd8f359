//! The open port's descriptor as the relay's reader and writer: read on tokio's
//! reactor, registered for reading only, and written straight to the descriptor.
//!
//! What this saves against a `SerialStream` split in two (docs/performance.md "What a
//! transaction costs"): the reader tells the reactor the port is drained when a read
//! returns less than it asked for, so the next read waits instead of returning
//! EAGAIN; and the port is not registered for writing, so the kernel's "room to
//! write" after every byte a pty's far end reads wakes nobody. A write the port has
//! no room for (flow control holding it back) registers a duplicate of the descriptor
//! for writing until a write goes through.

use crate::line::port::fd::{self, ReactorFd};
use std::io;
use std::os::fd::{AsFd, AsRawFd, FromRawFd, IntoRawFd, OwnedFd};
use std::pin::Pin;
use std::sync::Arc;
use std::task::{ready, Context, Poll};
use tokio::io::{AsyncRead, AsyncWrite, Interest, ReadBuf};

/// The port's descriptor on the reactor (`port/fd.rs`). Its exclusive hold (TIOCEXCL,
/// taken at open) is given back before it closes, as the serial crate's own close
/// does: the flag is the tty's, not the descriptor's, and a tty that outlives the
/// gateway (a pty whose far end lives on) would refuse the next start of the service
/// with EBUSY.
#[derive(Debug)]
struct HeldPort(ReactorFd);

impl Drop for HeldPort {
    fn drop(&mut self) {
        // SAFETY: TIOCNXCL takes no argument; the descriptor is open until `self.0`
        // drops, after this. Best effort: a port gone has nothing to give back.
        #[allow(unsafe_code)]
        unsafe {
            libc::ioctl(self.0.as_raw_fd(), libc::TIOCNXCL as _)
        };
    }
}

/// The read half: owns the descriptor's registration; the write half shares it.
#[derive(Debug)]
pub(crate) struct PortReader {
    fd: Arc<HeldPort>,
}

/// The write half.
#[derive(Debug)]
pub(crate) struct PortWriter {
    fd: Arc<HeldPort>,
    /// While the port has no room: a duplicate of its descriptor, registered for
    /// writing, to wait on.
    waiting: Option<ReactorFd>,
}

/// The two halves of the port opened as `port` (its settings made, held exclusively):
/// its descriptor is taken from it, set non-blocking and put on the current runtime's
/// reactor.
pub(crate) fn split(port: serialport::TTYPort) -> io::Result<(PortReader, PortWriter)> {
    // SAFETY: `into_raw_fd` gives up the descriptor, open, with nothing else owning it.
    #[allow(unsafe_code)]
    let fd = unsafe { OwnedFd::from_raw_fd(port.into_raw_fd()) };
    let fd = Arc::new(HeldPort(ReactorFd::new(fd, Interest::READABLE)?));
    Ok((
        PortReader { fd: fd.clone() },
        PortWriter { fd, waiting: None },
    ))
}

impl AsyncRead for PortReader {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        loop {
            let mut ready = ready!(self.fd.0.poll_read_ready(cx))?;
            let unfilled = buf.initialize_unfilled();
            let asked = unfilled.len();
            match ready.try_io(|fd| fd::read(fd.as_fd(), unfilled)) {
                Ok(Ok(n)) => {
                    // Less than asked: the port held no more. Waiting for the next
                    // edge is cheaper than a read that says EAGAIN; an edge that
                    // came after this read is kept (tokio clears only the readiness
                    // this guard saw). Not at end of file: that is said again.
                    if n > 0 && n < asked {
                        ready.clear_ready();
                    }
                    buf.advance(n);
                    return Poll::Ready(Ok(()));
                }
                Ok(Err(e)) => return Poll::Ready(Err(e)),
                // EAGAIN: readiness cleared by `try_io`; wait again.
                Err(_would_block) => continue,
            }
        }
    }
}

impl AsyncWrite for PortWriter {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        loop {
            if let Some(waiting) = &self.waiting {
                let mut ready = ready!(waiting.poll_write_ready(cx))?;
                match ready.try_io(|fd| fd::write(fd.as_fd(), buf)) {
                    Ok(Ok(n)) => {
                        self.waiting = None;
                        return Poll::Ready(Ok(n));
                    }
                    Ok(Err(e)) => return Poll::Ready(Err(e)),
                    Err(_would_block) => continue,
                }
            }
            match self.fd.0.write(buf) {
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    self.waiting = Some(self.fd.0.duplicate(Interest::WRITABLE)?);
                }
                done => return Poll::Ready(done),
            }
        }
    }

    fn poll_flush(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<io::Result<()>> {
        // Nothing is buffered here; the drain is the relay's (`Control::drain`).
        Poll::Ready(Ok(()))
    }

    fn poll_shutdown(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<io::Result<()>> {
        Poll::Ready(Ok(()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    /// A pty pair (`wire::pty::pair`, the device raw): the device end as a `TTYPort`,
    /// the master as a file.
    fn pty() -> (serialport::TTYPort, std::fs::File) {
        let (master, device) = crate::tools::wire::pty::pair().unwrap();
        // SAFETY: the descriptor is owned by `device`, given up here to the port.
        #[allow(unsafe_code)]
        let device = unsafe { serialport::TTYPort::from_raw_fd(device.into_raw_fd()) };
        (device, std::fs::File::from(master))
    }

    /// Bytes cross both ways, in pieces as they come; a read after a short read waits
    /// for the next bytes rather than ending; a write larger than the pty holds goes
    /// through as the far end reads it (the writer waits on its duplicate).
    #[tokio::test]
    async fn bytes_cross_both_ways_and_a_full_port_waits() {
        use std::io::{Read, Write};
        let (device, master) = pty();
        let (mut rd, mut wr) = split(device).unwrap();
        let mut far = master.try_clone().unwrap();
        far.write_all(b"abc").unwrap();
        let mut buf = [0u8; 16];
        let n = rd.read(&mut buf).await.unwrap();
        assert_eq!(&buf[..n], b"abc");
        // Nothing waiting now: the next read waits until bytes come.
        let later = tokio::spawn(async move {
            let mut buf = [0u8; 16];
            let n = rd.read(&mut buf).await.unwrap();
            buf[..n].to_vec()
        });
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
        assert!(!later.is_finished());
        far.write_all(b"de").unwrap();
        assert_eq!(later.await.unwrap(), b"de");

        // 256 KiB: more than a pty buffers; read on a thread as it comes.
        let want: Vec<u8> = (0..256 * 1024).map(|i| (i % 251) as u8).collect();
        let reader = std::thread::spawn(move || {
            let mut got = Vec::new();
            let mut chunk = [0u8; 4096];
            while got.len() < 256 * 1024 {
                let n = far.read(&mut chunk).unwrap();
                got.extend_from_slice(&chunk[..n]);
            }
            got
        });
        wr.write_all(&want).await.unwrap();
        assert_eq!(reader.join().unwrap(), want);
        assert!(
            wr.waiting.is_none(),
            "the duplicate is gone once a write went through"
        );
    }

    /// The exclusive hold taken at open is given back when both halves are gone: the
    /// tty's flag, read through another descriptor of it (root opens a port held
    /// exclusively all the same, so the flag itself is what is checked).
    #[tokio::test]
    async fn the_exclusive_hold_is_given_back_at_close() {
        let (device, _master) = pty();
        // SAFETY: F_DUPFD_CLOEXEC on an open descriptor; the copy is owned here.
        #[allow(unsafe_code)]
        let other = unsafe {
            OwnedFd::from_raw_fd(libc::fcntl(device.as_raw_fd(), libc::F_DUPFD_CLOEXEC, 0))
        };
        let excl = |fd: &OwnedFd| {
            let mut on: libc::c_int = 0;
            // SAFETY: TIOCGEXCL writes one int into `on`; the descriptor is open.
            #[allow(unsafe_code)]
            let r = unsafe { libc::ioctl(fd.as_raw_fd(), libc::TIOCGEXCL as _, &mut on) };
            assert_eq!(r, 0, "{}", io::Error::last_os_error());
            on
        };
        // SAFETY: TIOCEXCL takes no argument; the descriptor is open.
        #[allow(unsafe_code)]
        unsafe {
            libc::ioctl(other.as_raw_fd(), libc::TIOCEXCL as _)
        };
        assert_eq!(excl(&other), 1);
        let (rd, wr) = split(device).unwrap();
        drop(rd);
        assert_eq!(excl(&other), 1, "held while the writer lives");
        drop(wr);
        assert_eq!(excl(&other), 0, "given back at close");
    }
}
