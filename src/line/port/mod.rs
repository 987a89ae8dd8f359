//! What the relay is attached to: a byte transport it opens, reopens, reads, writes and
//! drains, with no knowledge of which one it is (docs/architecture.md "The ports").
//!
//! Three implementations: the serial port (`serial::SerialPort`, what the gateway
//! runs on), a TCP socket to a device server (`tcp::TcpPort`) and an in-memory pipe
//! ([`duplex::DuplexPort`], what the in-process relay tests drive). The relay holds a
//! `Box<dyn Port>`: one indirect call per read or write, next to a system call each.

pub mod duplex;
pub(crate) mod fd;
pub(crate) mod kind;
pub(crate) mod lifecycle;
pub mod serial;
pub(crate) mod tcp;
pub(crate) mod watch;

use std::future::Future;
use std::io;
use std::pin::Pin;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite};

/// The reading half of an open port.
pub(crate) type Reader = Box<dyn AsyncRead + Send + Unpin>;
/// The writing half of an open port.
pub(crate) type Writer = Box<dyn AsyncWrite + Send + Unpin>;
/// An open in progress ([`Port::open`]).
pub(crate) type Opening = Pin<Box<dyn Future<Output = io::Result<OpenPort>> + Send>>;
/// A wait until the bytes written have left ([`Control::drain`]): the instant they
/// had.
pub(crate) type Drain = Pin<Box<dyn Future<Output = io::Result<std::time::Instant>> + Send>>;

/// An open port: its two halves, read and written at once by the relay's loop, and
/// what it can tell about the bytes in transit.
pub struct OpenPort {
    /// Drain and input queries on the same transport. First, so that it drops first
    /// (fields drop in their order): a serial port's transmitter is switched off
    /// while its descriptor, which the halves below close, is still open.
    pub(crate) control: Box<dyn Control>,
    /// Bytes from the device.
    pub(crate) reader: Reader,
    /// Bytes to the device.
    pub(crate) writer: Writer,
    /// What the port turned out to be at this open (docs/reliability.md "Knowing the
    /// wire").
    pub(crate) info: kind::PortInfo,
}

impl std::fmt::Debug for OpenPort {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("OpenPort")
    }
}

/// What the relay may ask an open port besides reading and writing.
pub(crate) trait Control: Send {
    /// Starts waiting until everything written so far has left the port (a serial
    /// port's `tcdrain`): the reply timer and the inter-frame gap start from the last
    /// byte on the wire. A transport with no such notion is drained at once.
    fn drain(&self) -> io::Result<Drain> {
        Ok(Box::pin(async { Ok(std::time::Instant::now()) }))
    }

    /// Has the port received bytes not yet read? Then the device is talking, and an
    /// RTU/ASCII request must wait for them. A transport that cannot tell says no.
    fn input_waiting(&self) -> bool {
        false
    }

    /// Withdraws what was written and has not left the port yet (a serial port's
    /// output queue: TIOCOUTQ, then TCOFLUSH), and says how many bytes that was. A
    /// transport that cannot take bytes back withdraws none.
    fn withdraw_output(&self) -> io::Result<usize> {
        Ok(0)
    }

    /// Switches the RS-485 transmitter on (to send) or off (to receive), where the
    /// gateway drives it (`serial.direction`); elsewhere nothing to do.
    fn transmit(&mut self, _on: bool) -> io::Result<()> {
        Ok(())
    }

    /// Has the last stop bit of what was written left the port? An error says the
    /// port cannot tell (then the drain's answer stands for it).
    fn transmitter_empty(&self) -> io::Result<bool> {
        Err(io::Error::from(io::ErrorKind::Unsupported))
    }
}

/// A transport the relay can (re)open. Opening never blocks the runtime's thread: a
/// port that opens at once (a serial port, the in-memory pipe) returns a future that
/// is ready on its first poll, and the relay then uses it at once.
pub trait Port: Send {
    /// What the logs call it ("serial port").
    fn kind(&self) -> &'static str;
    /// Which one: the device path or the address.
    fn name(&self) -> &str;
    /// Opens it afresh, stale bytes cleared.
    fn open(&mut self) -> Opening;
    /// How long `bytes` take on the wire; zero for a transport with no line speed.
    fn wire_time(&self, bytes: usize) -> Duration;
    /// The device node it opens, watched while it is missing so that it is reopened
    /// as soon as it is back (`watch.rs`); none for a transport without one.
    fn node(&self) -> Option<&std::path::Path> {
        None
    }
}

/// Delays between attempts to (re)open a port: doubling from `min` up to `max`.
#[derive(Debug, Clone)]
pub(crate) struct Backoff {
    min: Duration,
    max: Duration,
    next: Duration,
}

impl Backoff {
    /// Starts at `min`.
    pub(crate) fn new(min: Duration, max: Duration) -> Self {
        Self {
            min,
            max,
            next: min,
        }
    }

    /// The delay before the next attempt; each call doubles the one after.
    pub(crate) fn next_delay(&mut self) -> Duration {
        let d = self.next;
        self.next = (self.next * 2).min(self.max);
        d
    }

    /// Back to `min` (the port opened).
    pub(crate) fn reset(&mut self) {
        self.next = self.min;
    }
}

/// Polls `opening` once: its result if it is ready at once, else the future back.
pub(crate) fn open_now(mut opening: Opening) -> Result<io::Result<OpenPort>, Opening> {
    let mut cx = std::task::Context::from_waker(std::task::Waker::noop());
    match opening.as_mut().poll(&mut cx) {
        std::task::Poll::Ready(r) => Ok(r),
        std::task::Poll::Pending => Err(opening),
    }
}

#[cfg(test)]
mod tests;
