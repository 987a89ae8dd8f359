//! The virtual line's two ends: a pseudo-terminal each, its device reached through a
//! symbolic link the user names, and what the program on it has set (its baud rate,
//! and the termios hints of its parity) read from the master side.

use super::uart::{ErrorHandling, Format, Parity};
use crate::line::port::fd::ReactorFd;
use std::io;
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd, RawFd};
use std::path::{Path, PathBuf};

/// One end: the pty's master (the line reads what the program writes, and writes what
/// it hears), its device held open too, and the link to it.
#[derive(Debug)]
pub(crate) struct PtyEnd {
    /// The master, non-blocking, on tokio's reactor (registered for reading).
    pub(crate) master: ReactorFd,
    /// The device end, held open by the line so that the master never reads EIO while
    /// no program has the device open, and its settings stay between programs.
    _device: OwnedFd,
    /// The device, /dev/pts/N.
    pub(crate) device: PathBuf,
    /// The link the user named, removed when the end is dropped.
    link: PathBuf,
}

/// What the program on an end has set, as its master reads it back.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct ProgramSettings {
    /// The output speed (termios2 `c_ospeed`).
    pub(crate) baud: u32,
    /// The parity and stop bits the termios still shows: a pty clears PARENB and
    /// CSIZE (it always reads back 8N1) but keeps PARODD, CSTOPB and INPCK, which
    /// serialport (mbgate's own ports) sets with any parity. 8 data bits.
    pub(crate) hinted: Format,
    /// How it takes bad characters (IGNPAR, INPCK, PARMRK, IGNBRK).
    pub(crate) handling: ErrorHandling,
}

impl PtyEnd {
    /// A new pty, raw (no echo, no line editing, until a program sets its own), with
    /// `link` pointing at its device. An existing symbolic link at `link` is replaced;
    /// anything else there is an error.
    pub(crate) fn open(link: &Path) -> io::Result<PtyEnd> {
        let (master, device) = pair()?;
        let master = ReactorFd::new(master, tokio::io::Interest::READABLE)?;
        let path = std::fs::read_link(format!("/proc/self/fd/{}", device.as_raw_fd()))?;
        match std::fs::symlink_metadata(link) {
            Ok(m) if m.file_type().is_symlink() => std::fs::remove_file(link)?,
            Ok(_) => {
                return Err(io::Error::new(
                    io::ErrorKind::AlreadyExists,
                    format!("{} exists and is not a symbolic link", link.display()),
                ))
            }
            Err(_) => {}
        }
        std::os::unix::fs::symlink(&path, link)?;
        Ok(PtyEnd {
            master,
            _device: device,
            device: path,
            link: link.to_path_buf(),
        })
    }

    /// What the program on this end has set.
    pub(crate) fn seen(&self) -> io::Result<ProgramSettings> {
        // On a master, TCGETS2 reads the device end's settings (the kernel's
        // tty_mode_ioctl takes the linked tty).
        let t = crate::line::port::serial::classic::get2(self.master.as_raw_fd())?;
        let parity = if t.c_cflag & libc::PARODD != 0 {
            Parity::Odd
        } else if t.c_iflag & libc::INPCK != 0 {
            Parity::Even
        } else {
            Parity::None
        };
        Ok(ProgramSettings {
            baud: t.c_ospeed,
            hinted: Format {
                data_bits: 8,
                parity,
                stop_bits: if t.c_cflag & libc::CSTOPB != 0 { 2 } else { 1 },
            },
            handling: ErrorHandling {
                ignore: t.c_iflag & libc::IGNPAR != 0,
                check: t.c_iflag & libc::INPCK != 0,
                mark: t.c_iflag & libc::PARMRK != 0,
                ignore_break: t.c_iflag & libc::IGNBRK != 0,
            },
        })
    }

    /// Reads what the program wrote, without blocking: `Ok(0)` when there is nothing.
    pub(crate) fn read(&self, buf: &mut [u8]) -> io::Result<usize> {
        zero_if_would_block(self.master.read(buf))
    }

    /// Hands bytes to the program, without blocking; how many the pty took (a program
    /// that does not read fills its buffer, and the rest are lost, as on a wire).
    pub(crate) fn write(&self, bytes: &[u8]) -> io::Result<usize> {
        zero_if_would_block(self.master.write(bytes))
    }
}

/// A read or write that would block moved no bytes: 0, not an error.
fn zero_if_would_block(r: io::Result<usize>) -> io::Result<usize> {
    match r {
        Err(e) if e.kind() == io::ErrorKind::WouldBlock => Ok(0),
        r => r,
    }
}

impl Drop for PtyEnd {
    fn drop(&mut self) {
        // Only our own link: a program may have put something else there since.
        if std::fs::read_link(&self.link).is_ok_and(|to| to == self.device) {
            let _ = std::fs::remove_file(&self.link);
        }
    }
}

/// A new pty pair, (master, device), both close-on-exec, the device raw (no echo, no
/// line editing, until a program sets its own).
pub fn pair() -> io::Result<(OwnedFd, OwnedFd)> {
    let (mut master, mut device): (RawFd, RawFd) = (-1, -1);
    // SAFETY: the two out-pointers are valid for the call; the name, termios and
    // window size are not asked for (null).
    #[allow(unsafe_code)]
    let r = unsafe {
        libc::openpty(
            &mut master,
            &mut device,
            std::ptr::null_mut(),
            std::ptr::null(),
            std::ptr::null(),
        )
    };
    if r != 0 {
        return Err(io::Error::last_os_error());
    }
    // SAFETY: both descriptors were just made, are valid and belong to nothing else.
    #[allow(unsafe_code)]
    let (master, device) = unsafe { (OwnedFd::from_raw_fd(master), OwnedFd::from_raw_fd(device)) };
    for fd in [master.as_raw_fd(), device.as_raw_fd()] {
        // SAFETY: plain fcntl calls on valid descriptors.
        #[allow(unsafe_code)]
        unsafe {
            libc::fcntl(fd, libc::F_SETFD, libc::FD_CLOEXEC);
        }
    }
    raw(device.as_raw_fd())?;
    Ok((master, device))
}

/// Raw mode on the device end (cfmakeraw), so nothing the line hands it is echoed back
/// or edited before a program sets its own; and 50 baud, a speed no program asks for,
/// so that the first program's settings always change the speed: Linux refuses
/// (EINVAL) a tcsetattr on a pty whose only change is a parity bit it cannot keep, as
/// pyserial's even parity at the pty's default 38400 baud would be.
fn raw(fd: RawFd) -> io::Result<()> {
    // SAFETY: termios is plain data; tcgetattr fills it before it is used.
    #[allow(unsafe_code)]
    let mut t: libc::termios = unsafe { std::mem::zeroed() };
    // SAFETY: valid descriptor and pointer for each call.
    #[allow(unsafe_code)]
    let r = unsafe {
        if libc::tcgetattr(fd, &mut t) != 0 {
            -1
        } else {
            libc::cfmakeraw(&mut t);
            libc::cfsetspeed(&mut t, libc::B50);
            libc::tcsetattr(fd, libc::TCSANOW, &t)
        }
    };
    if r != 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(())
}
