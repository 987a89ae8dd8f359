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
use crate::line::port::OpenPort;
use crate::line::woken::Woken;
use std::future::{poll_fn, Future};
use std::pin::Pin;
use std::task::{Context, Poll};
use tokio::io::ReadBuf;
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
    /// The clock as the loop last read it, before this wait.
    pub(super) now: Instant,
    /// Waits for `wake` to the microsecond; without it, tokio's timer does, to the
    /// millisecond.
    pub(super) timer: Option<&'a mut PreciseTimer>,
    /// The relay's one wait for shutdown; `None` once shutdown has been asked for.
    pub(super) shutdown: Option<&'a mut Woken<WaitForCancellationFutureOwned>>,
}

/// Long because it is the relay's one wait, every source polled in its turn in one
/// place, as one `select!` would be. Waits for the next event; bytes read go into
/// `rbuf`. One poll of each source in turn, bytes first, made by hand: no future made, moved and dropped for each
/// source at each wait (with `select!` over async blocks, about 600 instructions a
/// transaction more: callgrind, docs/performance.md "A transaction on a quiet line").
pub(super) async fn next(port: &mut Lifecycle, src: Sources<'_>, rbuf: &mut [u8]) -> Event {
    let Sources {
        mut commands,
        out,
        may_write,
        wake,
        now,
        mut timer,
        mut shutdown,
    } = src;
    // Tokio's timer, where there is no timerfd (or it failed): made when first needed.
    let mut sleep: Option<Pin<Box<tokio::time::Sleep>>> = None;
    let Lifecycle {
        state,
        drain,
        watch,
        ..
    } = port;
    poll_fn(move |cx| {
        // Biased, bytes first: a timer that finds bytes waiting must not take the
        // line for quiet (a held reply would be refuted, a frame cut).
        match &mut *state {
            State::Open(OpenPort { reader, writer, .. }) => {
                let mut buf = ReadBuf::new(rbuf);
                if let Poll::Ready(r) = Pin::new(&mut **reader).poll_read(cx, &mut buf) {
                    return Poll::Ready(Event::Read(r.map(|()| buf.filled().len())));
                }
                if let Some(event) = poll_command(cx, &mut commands) {
                    return Poll::Ready(event);
                }
                if !out.is_empty() && may_write {
                    if let Poll::Ready(w) = Pin::new(&mut **writer).poll_write(cx, out.pending()) {
                        return Poll::Ready(Event::Wrote(w));
                    }
                }
                if let Some(d) = drain {
                    if let Poll::Ready(r) = d.as_mut().poll(cx) {
                        return Poll::Ready(Event::Drained(r));
                    }
                }
            }
            State::Opening(opening) => {
                if let Poll::Ready(opened) = opening.as_mut().poll(cx) {
                    return Poll::Ready(Event::Opened(opened));
                }
                if let Some(event) = poll_command(cx, &mut commands) {
                    return Poll::Ready(event);
                }
            }
            // Until the next attempt, or the node back, whichever comes first.
            State::Closed { .. } => {
                if let Some(event) = poll_command(cx, &mut commands) {
                    return Poll::Ready(event);
                }
                if let Some(w) = watch {
                    if w.poll_changed(cx).is_ready() {
                        return Poll::Ready(Event::NodeChanged);
                    }
                }
            }
        }
        if let Some(at) = wake {
            if poll_timer(cx, at, now, &mut timer, &mut sleep).is_ready() {
                return Poll::Ready(Event::Timer);
            }
        }
        if let Some(s) = &mut shutdown {
            if Pin::new(&mut **s).poll(cx).is_ready() {
                return Poll::Ready(Event::Shutdown);
            }
        }
        Poll::Pending
    })
    .await
}

/// A command, if one came (or the end of them).
fn poll_command(cx: &mut Context<'_>, commands: &mut Option<&mut Commands>) -> Option<Event> {
    match commands.as_mut()?.poll_recv(cx) {
        Poll::Ready(cmd) => Some(Event::Command(cmd)),
        Poll::Pending => None,
    }
}

/// Ready once `at` has passed: to the microsecond on the timerfd, else (none, or it
/// failed) on tokio's timer, to the millisecond.
fn poll_timer(
    cx: &mut Context<'_>,
    at: Instant,
    now: Instant,
    timer: &mut Option<&mut PreciseTimer>,
    sleep: &mut Option<Pin<Box<tokio::time::Sleep>>>,
) -> Poll<()> {
    if sleep.is_none() {
        match timer.as_mut().map(|t| t.poll_until_from(cx, at, now)) {
            Some(Poll::Ready(Ok(()))) => return Poll::Ready(()),
            Some(Poll::Pending) => return Poll::Pending,
            Some(Poll::Ready(Err(e))) => {
                // Never seen: then tokio's timer.
                tracing::debug!("timerfd: {e}");
                *timer = None;
            }
            None => {}
        }
    }
    sleep
        .get_or_insert_with(|| Box::pin(tokio::time::sleep_until(at)))
        .as_mut()
        .poll(cx)
}
