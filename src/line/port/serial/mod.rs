//! The serial port, all of it: opening it with the configured settings, flow control,
//! stale bytes cleared, RS-485, exclusively (`open.rs`), with the classic termios
//! where termios2 is missing (`classic.rs`); what it is (`detect.rs`);
//! `tcdrain` and FIONREAD on its descriptor, the drain run by a thread of the port's
//! own (`drain.rs`); its descriptor as the relay's reader and writer (`stream.rs`);
//! the timer the line's gaps are kept with (`timer.rs`); and here,
//! the port as a [`Port`], with the switch of its RS-485 transmitter when the gateway
//! drives it (`direction.rs`). The simulator and the client open their ports with the same
//! [`open`]; how long bytes take at `baud_rate` is `port/kind.rs`'s.

pub(crate) mod classic;
mod detect;
pub mod direction;
mod drain;
mod open;
mod stream;
mod timer;

pub(crate) use detect::of_path;
pub use open::{held_by, open};
pub use timer::PreciseTimer;
pub(crate) use timer::{Deadline, Lateness};

use super::{Control, Drain, OpenPort, Opening, Port};
use crate::config::SerialConfig;
use std::io;
use std::os::fd::{AsRawFd, RawFd};
use std::time::Duration;

/// The `[serial]` port the gateway runs on.
#[derive(Debug)]
pub(crate) struct SerialPort {
    cfg: SerialConfig,
}

impl SerialPort {
    /// The port named and set up by `cfg`; nothing is opened yet.
    pub(crate) fn new(cfg: SerialConfig) -> Self {
        Self { cfg }
    }
}

impl Port for SerialPort {
    fn kind(&self) -> &'static str {
        "serial port"
    }

    fn name(&self) -> &str {
        &self.cfg.path
    }

    fn open(&mut self) -> Opening {
        // The switch is taken with the port: a port whose switch cannot be had is not
        // open, and is retried as a lost one is.
        let opened = open::open_tty(&self.cfg)
            .map_err(io::Error::other)
            .and_then(|port| {
                let fd = port.as_raw_fd();
                let transmitter = direction::take(&self.cfg, fd).map_err(io::Error::other)?;
                Ok((port, transmitter))
            });
        let low_latency = self.cfg.low_latency;
        Box::pin(async move {
            let (port, transmitter) = opened?;
            let fd = port.as_raw_fd();
            let info = detect::detect(fd, low_latency);
            let drainer = drain::Drainer::start(fd)?;
            let (reader, writer) = stream::split(port)?;
            Ok(OpenPort {
                reader: Box::new(reader),
                writer: Box::new(writer),
                control: Box::new(Tty {
                    fd,
                    drainer,
                    transmitter,
                }),
                info,
            })
        })
    }

    fn wire_time(&self, bytes: usize) -> Duration {
        super::kind::wire_time(&self.cfg, bytes)
    }

    fn node(&self) -> Option<&std::path::Path> {
        Some(std::path::Path::new(&self.cfg.path))
    }
}

/// The port's descriptor, valid while the two halves of its [`OpenPort`] live (the relay
/// drops all three together), its drain thread, which ends with it, and the switch of
/// its transmitter, left off when it drops.
struct Tty {
    fd: RawFd,
    drainer: drain::Drainer,
    transmitter: Option<direction::Transmitter>,
}

impl Control for Tty {
    fn drain(&self) -> io::Result<Drain> {
        let answered = self.drainer.drain()?;
        Ok(Box::pin(async move {
            answered
                .await
                .map_err(|_| io::Error::other("the drain thread is gone"))?
        }))
    }

    fn input_waiting(&self) -> bool {
        drain::input_waiting(self.fd).is_ok_and(|n| n > 0)
    }

    fn withdraw_output(&self) -> io::Result<usize> {
        drain::withdraw_output(self.fd)
    }

    fn transmit(&mut self, on: bool) -> io::Result<()> {
        match &mut self.transmitter {
            Some(t) => t.set(on),
            None => Ok(()),
        }
    }

    fn transmitter_empty(&self) -> io::Result<bool> {
        direction::transmitter_empty(self.fd)
    }
}
