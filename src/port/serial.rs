//! The serial port as a [`Port`]: the configured settings, flow control, stale bytes
//! cleared, RS-485, exclusive open (all in [`crate::serial::open`]), and `tcdrain` and
//! FIONREAD on its descriptor, the drain run off the runtime's thread.

use super::{Control, Drain, Link, Opening, Port};
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
        let opened = crate::serial::open(&self.cfg).map_err(io::Error::other);
        Box::pin(async move {
            let port = opened?;
            let fd = port.as_raw_fd();
            let (reader, writer) = tokio::io::split(port);
            Ok(Link {
                reader: Box::new(reader),
                writer: Box::new(writer),
                control: Box::new(Tty { fd }),
            })
        })
    }

    fn wire_time(&self, bytes: usize) -> Duration {
        crate::serial::wire_time(&self.cfg, bytes)
    }
}

/// The port's descriptor, valid while the two halves of its [`Link`] live (the relay
/// drops all three together).
struct Tty {
    fd: RawFd,
}

impl Control for Tty {
    fn drain(&self) -> io::Result<Drain> {
        let handle = crate::serial::drain(self.fd)?;
        Ok(Box::pin(
            async move { handle.await.map_err(io::Error::other)? },
        ))
    }

    fn input_waiting(&self) -> bool {
        crate::serial::input_waiting(self.fd).is_ok_and(|n| n > 0)
    }
}
