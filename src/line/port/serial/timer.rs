//! A timer finer than tokio's millisecond, for the line's gaps and turnarounds (a
//! timerfd on tokio's reactor): the relay's loop, the simulator and the benches wait
//! on it; and a deadline on one ([`Deadline`]) for a wait that is seldom moved (a
//! connection's idle timeout), kept out of tokio's timer.

use crate::line::port::fd::ReactorFd;
use std::future::Future;
use std::os::fd::{AsRawFd, FromRawFd};
use std::pin::Pin;
use std::task::{ready, Context, Poll};

/// A timer as precise as the kernel's (a timerfd on tokio's reactor): tokio's own
/// counts whole milliseconds and rounds a deadline up, which turns the 1750 µs gap
/// before an RTU request into 2 to 3 ms (docs/performance.md, "RTU at the line's
/// limit"). No thread and no spinning: the timerfd wakes the reactor's `epoll_wait`
/// at the instant it is set to.
#[derive(Debug)]
pub struct PreciseTimer {
    fd: ReactorFd,
    /// The instant it is set to go off.
    armed: Option<tokio::time::Instant>,
    /// How late its last wakes came, after the instant it was set to.
    late: Lateness,
}

/// A thread that sleeps wakes some tens of microseconds after its timer (the CPU's
/// wake from idle; docs/performance.md "What the limit is on this machine"): the
/// least of the last [`Lateness::KEPT`] such delays is how much earlier the timerfd
/// is set, so that the wake lands at the instant asked for rather than one wake-up
/// after it. A wake that still comes early is not returned: the timerfd is set again
/// for the instant itself, so [`PreciseTimer::until`] never returns before it.
/// The simulator keeps one too, for its replies' write after their instant.
#[derive(Debug, Default)]
pub(crate) struct Lateness {
    last: [u32; Lateness::KEPT],
    next: usize,
    seen: usize,
}

impl Lateness {
    const KEPT: usize = 16;
    /// Never earlier than this, whatever the wakes measured.
    const MOST: u32 = 200;

    /// A wake (or a write) `late` after its instant.
    pub(crate) fn record(&mut self, late: std::time::Duration) {
        let late_us = late.as_micros().min(u128::from(Self::MOST)) as u32;
        self.last[self.next] = late_us;
        self.next = (self.next + 1) % Self::KEPT;
        self.seen += 1;
    }

    /// How much earlier to set the timer: nothing until it has seen a few wakes.
    pub(crate) fn lead(&self) -> std::time::Duration {
        if self.seen < Self::KEPT {
            return std::time::Duration::ZERO;
        }
        let least = self.last.iter().copied().min().unwrap_or(0);
        std::time::Duration::from_micros(u64::from(least))
    }
}

impl PreciseTimer {
    /// A timer on the current runtime's reactor; an error where there is no timerfd.
    pub fn new() -> std::io::Result<PreciseTimer> {
        // SAFETY: no pointers; the descriptor returned is checked and then owned.
        #[allow(unsafe_code)]
        let fd = unsafe {
            libc::timerfd_create(
                libc::CLOCK_MONOTONIC,
                libc::TFD_NONBLOCK | libc::TFD_CLOEXEC,
            )
        };
        if fd < 0 {
            return Err(std::io::Error::last_os_error());
        }
        // SAFETY: `fd` was just made, is valid and belongs to nothing else.
        #[allow(unsafe_code)]
        let owned = unsafe { std::os::fd::OwnedFd::from_raw_fd(fd) };
        Ok(PreciseTimer {
            fd: ReactorFd::new(owned, tokio::io::Interest::READABLE)?,
            armed: None,
            late: Lateness::default(),
        })
    }

    /// Returns at `at`, or at once if it has passed; never before it. Sets the timerfd
    /// only when it is not already set to go off by `at` and after now: a loop that
    /// waits for a later instant each time (a new response deadline each transaction)
    /// leaves the earlier setting, is woken by it once, and only then sets the timerfd
    /// again, so a line polled without pause makes one system call for it each
    /// timeout's worth of transactions, not one each (docs/performance.md "What a
    /// transaction costs"). The timerfd is set earlier than `at` by the wake-up time
    /// its last wakes measured ([`Lateness`]).
    pub async fn until(&mut self, at: tokio::time::Instant) -> std::io::Result<()> {
        self.until_from(at, tokio::time::Instant::now()).await
    }

    /// [`PreciseTimer::until`], `now` being a reading of the clock taken before this
    /// call (a loop's own, which it has already read): one reading less a wait, and
    /// the timerfd, set relative to an earlier instant, still goes off no sooner than
    /// `at`.
    pub(crate) async fn until_from(
        &mut self,
        at: tokio::time::Instant,
        now: tokio::time::Instant,
    ) -> std::io::Result<()> {
        std::future::poll_fn(|cx| self.poll_until_from(cx, at, now)).await
    }

    /// [`PreciseTimer::until_from`] as a poll, for a loop that polls its sources
    /// itself (the relay's wait): ready once `at` has passed, never before. Each poll
    /// sets the timerfd only if it is not set already for `at` or for an earlier
    /// instant still to come, and reads the clock only once the timerfd went off.
    pub(crate) fn poll_until_from(
        &mut self,
        cx: &mut Context<'_>,
        at: tokio::time::Instant,
        now: tokio::time::Instant,
    ) -> Poll<std::io::Result<()>> {
        if at <= now {
            return Poll::Ready(Ok(()));
        }
        if !self.armed.is_some_and(|a| a > now && a <= at) {
            // Not so early that it is now: a timerfd set to zero is disarmed.
            let early = at.checked_sub(self.late.lead()).filter(|&e| e > now);
            self.arm(early.unwrap_or(at), now)?;
        }
        loop {
            let mut ready = ready!(self.fd.poll_read_ready(cx))?;
            // Readiness left over from an earlier setting says nothing about this one:
            // each expiry wakes the reactor anew (edge-triggered), so clearing it and
            // waiting again loses nothing.
            ready.clear_ready();
            let now = tokio::time::Instant::now();
            if let Some(armed) = self.armed.filter(|&a| a <= now) {
                self.late.record(now - armed);
            }
            if now >= at {
                return Poll::Ready(Ok(()));
            }
            // Woken by an earlier setting left in place, or early: now for `at` itself.
            if self.armed.is_none_or(|a| a <= now) {
                self.arm(at, now)?;
            }
        }
    }

    /// [`PreciseTimer::poll_until_from`], reading the clock first (a wait polled only
    /// when woken, [`Deadline`]).
    pub(crate) fn poll_until(
        &mut self,
        cx: &mut Context<'_>,
        at: tokio::time::Instant,
    ) -> Poll<std::io::Result<()>> {
        self.poll_until_from(cx, at, tokio::time::Instant::now())
    }

    /// Sets the timerfd to go off at `at`, `now` being before it.
    fn arm(&mut self, at: tokio::time::Instant, now: tokio::time::Instant) -> std::io::Result<()> {
        // Relative to a `now` read before the call: the kernel's clock has moved on
        // since, so it goes off at `at` or after, never before. (Setting it also zeroes
        // its count of expirations, so it is never read.)
        let rest = at - now;
        let spec = libc::itimerspec {
            it_interval: libc::timespec {
                tv_sec: 0,
                tv_nsec: 0,
            },
            it_value: libc::timespec {
                // `time_t` is 32 bits on some 32-bit targets: a wait that long is
                // capped at 68 years rather than wrapped.
                tv_sec: rest.as_secs().try_into().unwrap_or(i32::MAX.into()),
                tv_nsec: libc::c_long::from(rest.subsec_nanos() as i32),
            },
        };
        // SAFETY: `spec` is a valid itimerspec for the duration of the call; the old
        // value is not asked for (null).
        #[allow(unsafe_code)]
        let r =
            unsafe { libc::timerfd_settime(self.fd.as_raw_fd(), 0, &spec, std::ptr::null_mut()) };
        if r != 0 {
            return Err(std::io::Error::last_os_error());
        }
        self.armed = Some(at);
        Ok(())
    }
}

/// A wait for an instant that moves seldom and late (a connection's idle timeout: set
/// again only when it goes off), on a timerfd of its own. Where a tokio `Sleep` would
/// sit in tokio's timer, which every wait of the runtime's thread then consults (in
/// each `epoll_wait` of a transaction, about 450 instructions: callgrind,
/// docs/performance.md "A transaction on a quiet line"), this costs nothing until it
/// goes off. Made where there is no timerfd, it is tokio's `Sleep` after all.
#[derive(Debug)]
pub(crate) struct Deadline {
    at: tokio::time::Instant,
    on: DeadlineOn,
}

#[derive(Debug)]
enum DeadlineOn {
    Timerfd(PreciseTimer),
    Tokio(Pin<Box<tokio::time::Sleep>>),
}

impl Deadline {
    /// Goes off at `at`.
    pub(crate) fn new(at: tokio::time::Instant) -> Deadline {
        let on = match PreciseTimer::new() {
            Ok(t) => DeadlineOn::Timerfd(t),
            Err(e) => {
                tracing::debug!("no timerfd ({e}): tokio's timer");
                DeadlineOn::Tokio(Box::pin(tokio::time::sleep_until(at)))
            }
        };
        Deadline { at, on }
    }

    /// Goes off at `at` instead.
    pub(crate) fn reset(&mut self, at: tokio::time::Instant) {
        self.at = at;
        if let DeadlineOn::Tokio(sleep) = &mut self.on {
            sleep.as_mut().reset(at);
        }
    }
}

impl Future for Deadline {
    type Output = ();

    fn poll(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<()> {
        let this = self.get_mut();
        let at = this.at;
        match &mut this.on {
            DeadlineOn::Timerfd(t) => match ready!(t.poll_until(cx, at)) {
                Ok(()) => Poll::Ready(()),
                Err(e) => {
                    // Never seen: tokio's timer from now on.
                    tracing::debug!("timerfd: {e}");
                    let mut sleep = Box::pin(tokio::time::sleep_until(at));
                    let polled = sleep.as_mut().poll(cx);
                    this.on = DeadlineOn::Tokio(sleep);
                    polled
                }
            },
            DeadlineOn::Tokio(sleep) => sleep.as_mut().poll(cx),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    /// The timerfd is set early by the least of the last wakes' lateness, only once it
    /// has seen enough of them, and never by more than its bound.
    #[test]
    fn the_lead_is_the_least_recent_lateness() {
        let mut l = Lateness::default();
        for us in 0..Lateness::KEPT as u32 - 1 {
            l.record(Duration::from_micros(u64::from(40 + us)));
        }
        assert_eq!(l.lead(), Duration::ZERO, "not enough wakes seen");
        l.record(Duration::from_micros(90));
        assert_eq!(l.lead(), Duration::from_micros(40));
        for _ in 0..Lateness::KEPT {
            l.record(Duration::from_micros(10_000));
        }
        assert_eq!(
            l.lead(),
            Duration::from_micros(u64::from(Lateness::MOST)),
            "the old ones forgotten, the bound kept"
        );
        l.record(Duration::from_micros(7));
        assert_eq!(l.lead(), Duration::from_micros(7));
    }

    /// The timer goes off at its instant, not before and not a millisecond after (the
    /// bound is loose for a loaded machine; tokio's timer alone would take the 1750 µs
    /// to 2 or 3 ms, and the median of these is checked against 700 µs); an expiry
    /// nobody waited for does not end a later wait early.
    #[tokio::test]
    async fn precise_timer_is_neither_early_nor_a_tick_late() {
        use tokio::time::Instant;
        let mut timer = PreciseTimer::new().unwrap();
        let mut late = Vec::new();
        // Enough waits that the later ones are set early by what the first measured.
        for _ in 0..60 {
            let at = Instant::now() + Duration::from_micros(1750);
            timer.until(at).await.unwrap();
            let now = Instant::now();
            assert!(now >= at, "{:?} early", at - now);
            late.push(now - at);
        }
        late.sort();
        assert!(
            late[30] < Duration::from_micros(700),
            "median {:?} late",
            late[30]
        );

        // Set for 1 ms and dropped unwaited: it goes off while the reactor waits for
        // something else; a later, longer wait must not end with that expiry.
        let first = Instant::now() + Duration::from_millis(1);
        let _ = tokio::time::timeout(Duration::ZERO, timer.until(first)).await;
        tokio::time::sleep(Duration::from_millis(4)).await;
        let second = Instant::now() + Duration::from_millis(5);
        timer.until(second).await.unwrap();
        assert!(Instant::now() >= second, "woken by the earlier expiry");
        // An instant already past returns at once.
        timer.until(first).await.unwrap();

        // An instant nearer than the lead: the timerfd is set for it, not for now
        // (zero would disarm it, and the wait would never end).
        for _ in 0..Lateness::KEPT {
            timer
                .late
                .record(Duration::from_micros(Lateness::MOST.into()));
        }
        for _ in 0..5 {
            let at = Instant::now() + Duration::from_micros(50);
            tokio::time::timeout(Duration::from_secs(5), timer.until(at))
                .await
                .expect("a wait nearer than the lead ends")
                .unwrap();
            assert!(Instant::now() >= at);
        }
    }

    /// A deadline goes off at its instant, not before; moved later before it went
    /// off (its timerfd set for the earlier one), it goes off at the later one, and
    /// moved earlier, at the earlier one.
    #[tokio::test]
    async fn a_deadline_goes_off_at_its_instant_wherever_it_was_moved() {
        use tokio::time::Instant;
        let ms = Duration::from_millis;
        let start = Instant::now();
        let mut d = Deadline::new(start + ms(30));
        assert!(
            matches!(d.on, DeadlineOn::Timerfd(_)),
            "this machine has timerfd"
        );
        // Polled once (the timerfd set for 30 ms), then moved to 150 ms.
        assert!(tokio::time::timeout(ms(5), &mut d).await.is_err());
        d.reset(start + ms(150));
        (&mut d).await;
        let late = Instant::now();
        assert!(
            late >= start + ms(150),
            "{:?} early",
            start + ms(150) - late
        );
        // Moved to well before what it is set for: it goes off then.
        let now = Instant::now();
        d.reset(now + ms(600));
        assert!(tokio::time::timeout(ms(5), &mut d).await.is_err());
        d.reset(now + ms(40));
        tokio::time::timeout(ms(500), &mut d)
            .await
            .expect("moved earlier, it goes off then");
        assert!(Instant::now() >= now + ms(40));
    }
}
