//! What the line's timing asks of the port's descriptor: a thread of the port's own
//! that waits until everything written has left it (`tcdrain`), the bytes received
//! and not yet read (FIONREAD), and the bytes written and not yet sent, withdrawn
//! (TIOCOUTQ, TCOFLUSH).

use std::os::fd::{AsRawFd, BorrowedFd, RawFd};

/// What a drain answers: when `tcdrain` returned, or why it failed.
pub(crate) type Drained = std::io::Result<std::time::Instant>;

/// A thread of the port's own that waits, when asked, until everything written to the
/// port has left it (`tcdrain`), so the runtime's thread never blocks on it
/// (docs/performance.md, "RTU at the line's limit"). Made once when the port opens: it
/// owns a duplicate of the descriptor, made then (closing the port meanwhile cannot
/// make it touch another file), and each drain costs one wake of it and one of the
/// runtime, with no descriptor made and closed and no trip through tokio's blocking
/// pool. It ends, closing its duplicate, when the [`Drainer`] is dropped and the drain
/// it may be in has returned.
#[derive(Debug)]
pub(crate) struct Drainer {
    asks: std::sync::mpsc::Sender<tokio::sync::oneshot::Sender<Drained>>,
}

impl Drainer {
    /// Starts the thread for the open port `fd`.
    pub(crate) fn start(fd: RawFd) -> std::io::Result<Drainer> {
        // SAFETY: `fd` is the open port, borrowed only to duplicate it.
        #[allow(unsafe_code)]
        let owned = unsafe { BorrowedFd::borrow_raw(fd) }.try_clone_to_owned()?;
        let (asks, asked) = std::sync::mpsc::channel::<tokio::sync::oneshot::Sender<Drained>>();
        std::thread::Builder::new()
            .name("mbgate-drain".into())
            .spawn(move || {
                for answer in asked {
                    // SAFETY: a valid descriptor, ours until `owned` drops when the
                    // thread ends.
                    #[allow(unsafe_code)]
                    let r = unsafe { libc::tcdrain(owned.as_raw_fd()) };
                    // Dated here, not where the relay learns it: its thread may be
                    // scheduled late, and the gap counts from the last byte out.
                    let at = std::time::Instant::now();
                    let _ = answer.send(if r == 0 {
                        Ok(at)
                    } else {
                        Err(std::io::Error::last_os_error())
                    });
                }
            })?;
        Ok(Drainer { asks })
    }

    /// Asks for a drain of everything written so far; the answer comes on the
    /// receiver. An error says the thread is gone.
    pub(crate) fn drain(&self) -> std::io::Result<tokio::sync::oneshot::Receiver<Drained>> {
        let (answer, answered) = tokio::sync::oneshot::channel();
        self.asks
            .send(answer)
            .map_err(|_| std::io::Error::other("the drain thread is gone"))?;
        Ok(answered)
    }
}

/// Bytes received by the port `fd` and not yet read (FIONREAD).
pub(crate) fn input_waiting(fd: RawFd) -> std::io::Result<usize> {
    let mut n: libc::c_int = 0;
    // SAFETY: FIONREAD writes one int, which `n` is, for the duration of the call.
    #[allow(unsafe_code)]
    let r = unsafe { libc::ioctl(fd, libc::FIONREAD as _, &mut n as *mut libc::c_int) };
    if r == 0 {
        Ok(usize::try_from(n).unwrap_or(0))
    } else {
        Err(std::io::Error::last_os_error())
    }
}

/// Withdraws the bytes written to the port `fd` that have not left it (its output
/// queue: the tty's and the driver's, a USB adapter's included), and says how many
/// there were. Asked only after a request went unanswered, so it costs nothing while
/// the device answers. A pty's queue always reads empty (the bytes are already on
/// the other side), so there it withdraws nothing.
pub(crate) fn withdraw_output(fd: RawFd) -> std::io::Result<usize> {
    let mut n: libc::c_int = 0;
    // SAFETY: TIOCOUTQ writes one int, which `n` is, for the duration of the call.
    #[allow(unsafe_code)]
    let r = unsafe { libc::ioctl(fd, libc::TIOCOUTQ as _, &mut n as *mut libc::c_int) };
    if r != 0 {
        return Err(std::io::Error::last_os_error());
    }
    let n = usize::try_from(n).unwrap_or(0);
    if n > 0 {
        // SAFETY: a plain call on the open port's descriptor; no memory is passed.
        #[allow(unsafe_code)]
        let r = unsafe { libc::tcflush(fd, libc::TCOFLUSH) };
        if r != 0 {
            return Err(std::io::Error::last_os_error());
        }
    }
    Ok(n)
}
