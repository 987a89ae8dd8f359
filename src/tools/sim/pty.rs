//! A pty the simulator makes itself (`mbgate sim --pty LINK`): the device on the pty's
//! master, a link at LINK to its slave for the gateway to open, and no socat between.
//!
//! A socat pair puts a relay process between the two ends: each byte crosses two ptys
//! and waits for socat's wake-up on the way (a device that answers at once is seen at
//! 0.39 to 0.45 ms through one, 0.29 to 0.36 ms on a pty of its own: docs/performance.md
//! "A replayed device's reply time"). A replayed device's reply time already holds the
//! path it was recorded through, so a replay served through a second socat pair counts
//! that path twice; on its own pty it counts it once, less the round trip measured.
//!
//! The simulator keeps the slave open itself, so the gateway may close and reopen it
//! (a reload, a lost line) without the master reading a hang-up.

use crate::line::port::fd::ReactorFd;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_serial::{SerialPort, SerialStream};

/// Why the pty could not be made or named.
#[derive(Debug, thiserror::Error)]
pub(crate) enum PtyError {
    /// The kernel gave no pty (none left, or no /dev/ptmx).
    #[error("cannot make a pty: {0}")]
    Make(std::io::Error),
    /// The pty's slave has no path to link to.
    #[error("the pty has no name")]
    Unnamed,
    /// Only a link (a stale one, from a run that was killed) is replaced.
    #[error("{} exists and is not a link: not replaced", .0.display())]
    NotALink(PathBuf),
    /// The link could not be made (a missing folder, no right to write there).
    #[error("cannot link {} to {slave}: {source}", .link.display())]
    Link {
        /// Where the link was asked for.
        link: PathBuf,
        /// The pty's slave.
        slave: String,
        /// What the system said.
        source: std::io::Error,
    },
}

/// The pty's slave, held open, and the link to it, removed when dropped.
#[derive(Debug)]
pub(crate) struct OwnPty {
    link: PathBuf,
    slave: String,
    round_trip: Duration,
    _held: SerialStream,
}

/// How many bytes measure the pty's round trip: enough for a steady median, a few
/// milliseconds at start.
const ROUNDS: usize = 64;

impl OwnPty {
    /// Makes the pty, measures its round trip, links `link` to its slave, and gives
    /// the master end to serve.
    pub(crate) async fn make(link: &Path) -> Result<(SerialStream, OwnPty), PtyError> {
        let (mut master, held) = SerialStream::pair().map_err(|e| PtyError::Make(e.into()))?;
        let slave = held.name().ok_or(PtyError::Unnamed)?;
        // Before the link exists: nobody else is on the slave yet.
        let round_trip = round_trip(&mut master, &slave)
            .await
            .map_err(PtyError::Make)?;
        match std::fs::symlink_metadata(link) {
            Ok(m) if m.file_type().is_symlink() => {
                let _ = std::fs::remove_file(link);
            }
            Ok(_) => return Err(PtyError::NotALink(link.to_path_buf())),
            Err(_) => {}
        }
        std::os::unix::fs::symlink(&slave, link).map_err(|source| PtyError::Link {
            link: link.to_path_buf(),
            slave: slave.clone(),
            source,
        })?;
        let own = OwnPty {
            link: link.to_path_buf(),
            slave,
            round_trip,
            _held: held,
        };
        Ok((master, own))
    }

    /// The slave's own name (`/dev/pts/N`).
    pub(crate) fn slave(&self) -> &str {
        &self.slave
    }

    /// The median time a byte took from the master to a program blocked on the slave
    /// and back, measured at start: what this pty and the two wake-ups on it add to
    /// any reply, whatever the device's own time.
    pub(crate) fn round_trip(&self) -> Duration {
        self.round_trip
    }
}

/// A byte written on the master, echoed by a program reading the slave as a
/// gateway's line task does (an event loop woken by the reactor, on its own thread),
/// read back on the master as the simulator reads: the median of [`ROUNDS`].
async fn round_trip(master: &mut SerialStream, slave: &str) -> std::io::Result<Duration> {
    use std::os::unix::fs::OpenOptionsExt;
    let far = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags(libc::O_NONBLOCK | libc::O_NOCTTY)
        .open(slave)?;
    let echo = std::thread::spawn(move || -> std::io::Result<()> {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_io()
            .build()?;
        rt.block_on(async move {
            let far = ReactorFd::new(far.into(), tokio::io::Interest::READABLE)?;
            let mut b = [0u8; 1];
            let mut echoed = 0;
            while echoed < ROUNDS {
                let mut ready = far.readable().await?;
                match far.read(&mut b) {
                    Ok(1) => {
                        // One byte into an empty pty: the write never waits.
                        far.write(&b)?;
                        echoed += 1;
                    }
                    Ok(_) => return Err(std::io::ErrorKind::UnexpectedEof.into()),
                    Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => ready.clear_ready(),
                    Err(e) => return Err(e),
                }
            }
            Ok(())
        })
    });
    let mut times = Vec::with_capacity(ROUNDS);
    let mut b = [0u8; 1];
    for i in 0..ROUNDS {
        let start = Instant::now();
        AsyncWriteExt::write_all(master, &[i as u8]).await?;
        AsyncReadExt::read_exact(master, &mut b).await?;
        times.push(start.elapsed());
        if b[0] != i as u8 {
            return Err(std::io::Error::other("the pty's echo came back changed"));
        }
    }
    echo.join()
        .map_err(|_| std::io::Error::other("the pty's echo thread failed"))??;
    times.sort();
    Ok(times[ROUNDS / 2])
}

impl Drop for OwnPty {
    /// The link goes with the pty, unless another program has put its own there since.
    fn drop(&mut self) {
        if std::fs::read_link(&self.link).is_ok_and(|t| t == Path::new(&self.slave)) {
            let _ = std::fs::remove_file(&self.link);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    #[tokio::test]
    async fn the_link_reaches_the_master_and_goes_with_it() {
        let dir = std::env::temp_dir().join(format!("mbgate-pty-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let link = dir.join("ttyDEV");
        // A stale link from a killed run is replaced.
        std::os::unix::fs::symlink("/nonexistent", &link).unwrap();
        let (mut master, own) = OwnPty::make(&link).await.unwrap();
        assert!(own.round_trip() > Duration::ZERO);
        assert_eq!(std::fs::read_link(&link).unwrap(), Path::new(own.slave()));
        let mut far = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .open(&link)
            .unwrap();
        far.write_all(b"\x01\x03").unwrap();
        let mut got = [0u8; 2];
        master.read_exact(&mut got).await.unwrap();
        assert_eq!(got, *b"\x01\x03");
        // The far end closes; the master still writes, and a new open reads it.
        drop(far);
        AsyncWriteExt::write_all(&mut master, b"\x05")
            .await
            .unwrap();
        drop(own);
        assert!(
            std::fs::symlink_metadata(&link).is_err(),
            "the link is gone"
        );
        // A file that is not a link is never replaced.
        std::fs::write(&link, b"mine").unwrap();
        assert!(matches!(
            OwnPty::make(&link).await,
            Err(PtyError::NotALink(_))
        ));
        assert_eq!(std::fs::read(&link).unwrap(), b"mine");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
