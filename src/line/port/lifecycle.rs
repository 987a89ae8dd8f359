//! A line's port through its life, the same for every line (the relay's, the master
//! line's): closed until the next attempt, opening, open; opened and reopened with
//! backoff, and at once when its device node comes back (`watch.rs`); lost; each
//! outage said once when it begins and once, with its length, when it ends; and what
//! the loop asks of an open port (bytes waiting to be read, the wait until written
//! bytes have left).

use crate::line::port::kind::PortInfo;
use crate::line::port::watch::NodeWatch;
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
    /// While closed, a port with a device node: the watch for it to come back
    /// (waited on with `watch::changed`, then [`Lifecycle::retry_now`]).
    pub(crate) watch: Option<NodeWatch>,
    /// When the outage under way began: the port was lost, or its first open failed.
    down_since: Option<Instant>,
    /// How long the outage that the last open ended lasted, for its log line.
    back_after: Option<Duration>,
    /// When the port last opened: one lost soon after is retried no sooner than the
    /// backoff says (a node that opens and fails at once is not hammered).
    opened_at: Option<Instant>,
    /// When the last open was tried: a wake of the watch brings the next no sooner
    /// than [`WAKE_GAP`] after it.
    tried_at: Option<Instant>,
    /// When the watch last said the node may be back: an open that fails within
    /// [`SETTLING`] of it is tried again after [`SETTLE_STEP`], not the backoff.
    woken_at: Option<Instant>,
}

/// The least time between two attempts to open that the watch's wakes bring: a
/// process that makes and removes the awaited name in a loop (where it may write that
/// directory) costs at most 50 attempts a second.
const WAKE_GAP: Duration = Duration::from_millis(20);

/// How long after a wake of the watch a node that is there but does not open yet is
/// tried again every [`SETTLE_STEP`]. The kernel makes a USB adapter's node before its
/// driver and udev are done with it (its mode and owner, the port's setup); an open
/// in between fails, and what makes it succeed may change nothing the watch sees, so
/// the backoff's next attempt (up to 2 s) would be the next: in the emulated Pi's ring
/// 2 of 20 outages came back 1.6 and 2.0 s after udev's event that way
/// (docs/raspberry-pi.md "When the adapter is pulled out"). At most 20 attempts a wake.
const SETTLING: Duration = Duration::from_secs(2);

/// The step of the attempts while a node settles ([`SETTLING`]).
const SETTLE_STEP: Duration = Duration::from_millis(100);

/// A port lost after being open this long is retried at once; one lost sooner goes on
/// with the backoff where it was.
const STEADY: Duration = Duration::from_secs(1);

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
            watch: None,
            down_since: None,
            back_after: None,
            opened_at: None,
            tried_at: None,
            woken_at: None,
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
        self.tried_at = Some(now);
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
                self.warned = false;
                self.watch = None;
                self.back_after = self
                    .down_since
                    .take()
                    .map(|s| now.saturating_duration_since(s));
                self.opened_at = Some(now);
                self.woken_at = None;
                Some(info)
            }
            Err(e) => {
                self.down_since.get_or_insert(now);
                self.watch_for_node();
                let delay = self.next_delay(now);
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

    /// Says the port is open: what it turned out to be (`info`), how the line times
    /// it (`timing`) and, when this open ended an outage, how long that lasted.
    pub(crate) fn tell_open(&self, info: &PortInfo, timing: &str) {
        let kind = self.transport.kind();
        match self.back_after {
            Some(d) => info!(
                path = %self.transport.name(),
                baud = self.baud,
                outage_ms = d.as_millis() as u64,
                "{kind} open: {info}; {timing}; back after an outage of {:.3} s",
                d.as_secs_f64()
            ),
            None => info!(
                path = %self.transport.name(),
                baud = self.baud,
                "{kind} open: {info}; {timing}"
            ),
        }
    }

    /// The port failed or its far end went away: closed at once (its descriptor with
    /// it, so the kernel may give a USB adapter plugged back in its old name), reopened
    /// with backoff, or as soon as its node is back.
    pub(crate) fn lost(&mut self, why: &str, now: Instant) {
        let kind = self.transport.kind();
        warn!(
            path = %self.transport.name(),
            "{kind} lost: {why}; reopening with backoff, {}",
            self.meanwhile
        );
        if self
            .opened_at
            .is_some_and(|at| now.saturating_duration_since(at) >= STEADY)
        {
            self.backoff.reset();
        }
        self.state = State::Closed {
            retry_at: now + self.backoff.next_delay(),
        };
        self.warned = true;
        self.drain = None;
        self.down_since = Some(now);
        self.woken_at = None;
        self.watch_for_node();
    }

    /// How long until the next attempt after one that failed `now`: a step while the
    /// node settles after a wake of the watch, else the backoff's next delay.
    fn next_delay(&mut self, now: Instant) -> Duration {
        match self.woken_at {
            Some(w) if now.saturating_duration_since(w) < SETTLING => SETTLE_STEP,
            _ => self.backoff.next_delay(),
        }
    }

    /// When the outage under way began, if the port is in one.
    pub(crate) fn down_since(&self) -> Option<Instant> {
        self.down_since
    }

    /// Watches for the port's device node to come back, where it has one (a serial
    /// port: the path as configured, links followed anew each time).
    fn watch_for_node(&mut self) {
        match &mut self.watch {
            Some(w) => w.rearm(),
            None => self.watch = self.transport.node().and_then(NodeWatch::new),
        }
    }

    /// The node may be back: the next open is due now, or [`WAKE_GAP`] after the last.
    pub(crate) fn retry_now(&mut self, now: Instant) {
        let soonest = self.tried_at.map_or(now, |t| now.max(t + WAKE_GAP));
        self.woken_at = Some(now);
        if let State::Closed { retry_at } = &mut self.state {
            *retry_at = soonest.min(*retry_at);
            debug!(
                path = %self.transport.name(),
                "{} may be back: next attempt in {} ms",
                self.transport.kind(),
                retry_at.saturating_duration_since(now).as_millis()
            );
        }
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A port that is never there.
    struct Missing;

    impl port::Port for Missing {
        fn kind(&self) -> &'static str {
            "serial port"
        }
        fn name(&self) -> &str {
            "/nonexistent/ttyUSB0"
        }
        fn open(&mut self) -> Opening {
            Box::pin(async { Err(std::io::Error::from(std::io::ErrorKind::NotFound)) })
        }
        fn wire_time(&self, _: usize) -> Duration {
            Duration::ZERO
        }
    }

    /// A wake of the watch makes the next attempt due at once, but never sooner than
    /// WAKE_GAP after the last (a name made and removed in a loop is not a loop of
    /// opens), and never later than the backoff had it.
    #[test]
    fn a_wake_brings_the_next_attempt_forward_no_closer_than_the_gap() {
        let t0 = Instant::now();
        let mut port = Lifecycle::new(Box::new(Missing), 9600, t0);
        let failed = port.open_if_due(t0).expect("due at once");
        assert!(port.opened(failed, t0).is_none());
        assert_eq!(port.down_since(), Some(t0));
        assert_eq!(port.retry_at(), Some(t0 + Duration::from_millis(100)));
        port.retry_now(t0 + Duration::from_millis(5));
        assert_eq!(port.retry_at(), Some(t0 + WAKE_GAP));
        port.retry_now(t0 + Duration::from_millis(50));
        assert_eq!(
            port.retry_at(),
            Some(t0 + WAKE_GAP),
            "not later than it was"
        );
        let at = t0 + Duration::from_millis(60);
        let failed = port.open_if_due(at).expect("due");
        port.opened(failed, at);
        assert_eq!(port.down_since(), Some(t0), "the same outage");
        port.retry_now(at);
        assert_eq!(port.retry_at(), Some(at + WAKE_GAP));
    }

    /// A node there that does not open yet after a wake is tried again every
    /// SETTLE_STEP for SETTLING after the wake, then with the backoff again: the port
    /// opens within a step of becoming ready, though nothing the watch sees changed.
    #[test]
    fn after_a_wake_a_node_that_does_not_open_yet_is_tried_every_step() {
        let t0 = Instant::now();
        let mut port = Lifecycle::new(Box::new(Missing), 9600, t0);
        // An outage long enough for the backoff to have grown to its ceiling.
        let mut at = t0;
        for _ in 0..8 {
            let failed = port.open_if_due(at).expect("due");
            port.opened(failed, at);
            at = port.retry_at().expect("closed");
        }
        let woke = at;
        port.retry_now(woke);
        assert_eq!(port.retry_at(), Some(woke));
        let mut tried = woke;
        let mut attempts = 0;
        while tried < woke + SETTLING {
            let failed = port.open_if_due(tried).expect("due");
            port.opened(failed, tried);
            attempts += 1;
            let next = port.retry_at().expect("closed");
            assert_eq!(next, tried + SETTLE_STEP, "attempt {attempts}");
            tried = next;
        }
        assert_eq!(attempts, 20, "one attempt a step for SETTLING");
        // The wake's time is over: the backoff again, at its ceiling (2 s).
        let failed = port.open_if_due(tried).expect("due");
        port.opened(failed, tried);
        let gap = port.retry_at().expect("closed") - tried;
        assert_eq!(gap, Duration::from_secs(2));
    }
}
