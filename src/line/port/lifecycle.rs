//! A line's port through its life, the same for every line (the relay's, the master
//! line's): closed until the next attempt, opening, open; opened and reopened with
//! backoff, lost; and what the loop asks of an open port (bytes waiting to be read,
//! the wait until written bytes have left).

use crate::line::port::kind::PortInfo;
use crate::line::port::{self, Backoff, OpenPort, Opening};
use std::time::Duration;
use tokio::time::Instant;
use tracing::{debug, info, warn};

/// Where the port is in its life.
pub(crate) enum State {
    Open(OpenPort),
    /// An open that did not finish at once (a TCP connect).
    Opening(Opening),
    Closed {
        retry_at: Instant,
    },
}

/// A line's port: any transport, opened and reopened with backoff.
pub(crate) struct Lifecycle {
    pub(crate) state: State,
    /// Waiting for the last write to leave the port (RTU/ASCII).
    pub(crate) drain: Option<port::Drain>,
    /// What `state` opens: the line never learns which transport it is.
    transport: Box<dyn port::Port>,
    backoff: Backoff,
    /// A failed open was logged at warning level: the next are logged at debug.
    warned: bool,
    /// For the log line when it opens.
    baud: u32,
    /// What the log says happens while the port cannot be opened.
    meanwhile: &'static str,
}

impl Lifecycle {
    /// Closed, its first open due at `now`.
    pub(crate) fn new(transport: Box<dyn port::Port>, baud: u32, now: Instant) -> Self {
        Self {
            state: State::Closed { retry_at: now },
            drain: None,
            transport,
            backoff: Backoff::new(Duration::from_millis(100), Duration::from_secs(2)),
            warned: false,
            baud,
            meanwhile: "answering 0x0A meanwhile",
        }
    }

    /// What the log says happens while the port cannot be opened (a relay:
    /// "answering 0x0A meanwhile").
    pub(crate) fn meanwhile(mut self, said: &'static str) -> Self {
        self.meanwhile = said;
        self
    }

    pub(crate) fn set_transport(&mut self, transport: Box<dyn port::Port>) {
        self.transport = transport;
    }

    pub(crate) fn is_open(&self) -> bool {
        matches!(self.state, State::Open(_))
    }

    /// When the next open is due, while closed.
    pub(crate) fn retry_at(&self) -> Option<Instant> {
        match self.state {
            State::Closed { retry_at } => Some(retry_at),
            _ => None,
        }
    }

    /// Starts an open if one is due at `now`; gives back its result if it finished at
    /// once (then pass it to [`Lifecycle::opened`]).
    pub(crate) fn open_if_due(&mut self, now: Instant) -> Option<std::io::Result<OpenPort>> {
        let retry_at = self.retry_at()?;
        if now < retry_at {
            return None;
        }
        match port::open_now(self.transport.open()) {
            Ok(opened) => Some(opened),
            Err(opening) => {
                self.state = State::Opening(opening);
                None
            }
        }
    }

    /// An open finished: what the port turned out to be if it is now open (the line
    /// starts afresh; then [`Lifecycle::tell_open`]), else the next attempt is due
    /// later.
    pub(crate) fn opened(
        &mut self,
        opened: std::io::Result<OpenPort>,
        now: Instant,
    ) -> Option<PortInfo> {
        let kind = self.transport.kind();
        match opened {
            Ok(link) => {
                let info = link.info.clone();
                self.state = State::Open(link);
                self.backoff.reset();
                self.warned = false;
                Some(info)
            }
            Err(e) => {
                let delay = self.backoff.next_delay();
                if self.warned {
                    debug!(path = %self.transport.name(), "{kind} still unavailable: {e}");
                } else {
                    warn!(
                        path = %self.transport.name(),
                        "{kind} unavailable: {e}; retrying with backoff, {}",
                        self.meanwhile
                    );
                    self.warned = true;
                }
                self.state = State::Closed {
                    retry_at: now + delay,
                };
                None
            }
        }
    }

    /// Says the port is open: what it turned out to be (`info`) and how the line
    /// times it (`timing`).
    pub(crate) fn tell_open(&self, info: &PortInfo, timing: &str) {
        let kind = self.transport.kind();
        info!(
            path = %self.transport.name(),
            baud = self.baud,
            "{kind} open: {info}; {timing}"
        );
    }

    /// The port failed or its far end went away: closed, reopened with backoff.
    pub(crate) fn lost(&mut self, why: &str, now: Instant) {
        let kind = self.transport.kind();
        warn!(path = %self.transport.name(), "{kind} lost: {why}; reopening with backoff");
        self.state = State::Closed {
            retry_at: now + self.backoff.next_delay(),
        };
        self.warned = true;
        self.drain = None;
    }

    /// Has the port received bytes the relay has not read yet?
    pub(crate) fn input_waiting(&self) -> bool {
        match &self.state {
            State::Open(link) => link.control.input_waiting(),
            _ => false,
        }
    }

    /// Withdraws what the port has not sent yet (a serial port's output queue), and
    /// says how many bytes; none where it is not open or cannot tell.
    pub(crate) fn withdraw_output(&self) -> std::io::Result<usize> {
        match &self.state {
            State::Open(link) => link.control.withdraw_output(),
            _ => Ok(0),
        }
    }

    /// Switches the RS-485 transmitter on or off (where the gateway drives it).
    pub(crate) fn transmit(&mut self, on: bool) -> std::io::Result<()> {
        match &mut self.state {
            State::Open(link) => link.control.transmit(on),
            _ => Ok(()),
        }
    }

    /// Has the last stop bit left the port? An error: it cannot tell.
    pub(crate) fn transmitter_empty(&self) -> std::io::Result<bool> {
        match &self.state {
            State::Open(link) => link.control.transmitter_empty(),
            _ => Ok(true),
        }
    }

    /// Starts waiting for the bytes written to leave the port, off the runtime's
    /// thread; an error says the port cannot tell (time from the write instead).
    pub(crate) fn start_drain(&mut self) -> std::io::Result<()> {
        if let State::Open(link) = &self.state {
            self.drain = Some(link.control.drain()?);
        }
        Ok(())
    }

    /// How long `bytes` take on the wire.
    pub(crate) fn wire_time(&self, bytes: usize) -> Duration {
        self.transport.wire_time(bytes)
    }
}
