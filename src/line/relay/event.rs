//! What the relay's loop waits on, as one [`Event`]: a command from a connection, bytes
//! from the port, room to write, the end of a drain, an open that finished, the closed
//! port's device node back, the next
//! timer (to the microsecond, on a timerfd set only when the next wake moves: no
//! self-wake of tokio's reactor for each new deadline), or shutdown. The waiting only: the loop decides what each event means.

use super::command::Commands;
use super::outgoing::Outgoing;
use super::Command;
use crate::line::port::lifecycle::{Lifecycle, State};
use crate::line::port::serial::PreciseTimer;
use crate::line::port::watch;
use crate::line::port::OpenPort;
use crate::line::woken::Woken;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::time::Instant;
use tokio_util::sync::WaitForCancellationFutureOwned;

pub(super) enum Event {
    Command(Option<Command>),
    Read(std::io::Result<usize>),
    Wrote(std::io::Result<usize>),
    /// When the last byte left (the drain thread's clock), or why it cannot tell.
    Drained(std::io::Result<std::time::Instant>),
    Opened(std::io::Result<OpenPort>),
    /// The closed port's device node may be back (`crate::line::port::watch`).
    NodeChanged,
    Timer,
    Shutdown,
}

/// Everything besides the port the loop may wake for.
pub(super) struct Sources<'a> {
    /// `None` once every handle is gone: `recv` would return at once forever.
    pub(super) commands: Option<&'a mut Commands>,
    /// Written while it holds bytes.
    pub(super) out: &'a Outgoing,
    /// The transmitter is on and its delay before has passed (always, where the
    /// gateway switches none).
    pub(super) may_write: bool,
    /// The next timer, if any.
    pub(super) wake: Option<Instant>,
    /// Waits for `wake` to the microsecond; without it, tokio's timer does, to the
    /// millisecond.
    pub(super) timer: Option<&'a mut PreciseTimer>,
    /// The relay's one wait for shutdown; `None` once shutdown has been asked for.
    pub(super) shutdown: Option<&'a mut Woken<WaitForCancellationFutureOwned>>,
}

/// Waits for the next event; bytes read go into `rbuf`.
pub(super) async fn next(port: &mut Lifecycle, src: Sources<'_>, rbuf: &mut [u8]) -> Event {
    let Sources {
        mut commands,
        out,
        may_write,
        wake,
        timer,
        shutdown,
    } = src;
    let has_wake = wake.is_some();
    let timer = async {
        let at = wake.expect("guarded");
        match timer {
            Some(t) => {
                if let Err(e) = t.until(at).await {
                    // Never seen: then tokio's timer.
                    tracing::debug!("timerfd: {e}");
                    tokio::time::sleep_until(at).await;
                }
            }
            None => tokio::time::sleep_until(at).await,
        }
    };
    let has_commands = commands.is_some();
    let command = async { commands.as_mut().expect("guarded").recv().await };
    let has_shutdown = shutdown.is_some();
    let shutdown = async { shutdown.expect("guarded").await };
    let drain = &mut port.drain;
    let watch = &mut port.watch;
    match &mut port.state {
        // Biased, bytes first: a timer that finds bytes waiting must not take the
        // line for quiet (a held reply would be refuted, a frame cut).
        State::Open(OpenPort {
            reader: rd,
            writer: wr,
            ..
        }) => tokio::select! {
            biased;
            r = rd.read(rbuf) => Event::Read(r),
            cmd = command, if has_commands => Event::Command(cmd),
            w = wr.write(out.pending()), if !out.is_empty() && may_write => Event::Wrote(w),
            d = async { drain.as_mut().expect("guarded").await }, if drain.is_some() => Event::Drained(d),
            _ = timer, if has_wake => Event::Timer,
            _ = shutdown, if has_shutdown => Event::Shutdown,
        },
        State::Opening(opening) => tokio::select! {
            opened = opening => Event::Opened(opened),
            cmd = command, if has_commands => Event::Command(cmd),
            _ = timer, if has_wake => Event::Timer,
            _ = shutdown, if has_shutdown => Event::Shutdown,
        },
        // Until the next attempt, or the node back, whichever comes first.
        State::Closed { .. } => tokio::select! {
            cmd = command, if has_commands => Event::Command(cmd),
            _ = watch::changed(watch), if watch.is_some() => Event::NodeChanged,
            _ = timer, if has_wake => Event::Timer,
            _ = shutdown, if has_shutdown => Event::Shutdown,
        },
    }
}
