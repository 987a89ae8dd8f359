//! A timer finer than tokio's millisecond, for the line's gaps and turnarounds (a
//! timerfd on tokio's reactor): the relay's loop, the simulator and the benches wait
//! on it.

use std::os::fd::{AsRawFd, FromRawFd};

/// A timer as precise as the kernel's (a timerfd on tokio's reactor): tokio's own
/// counts whole milliseconds and rounds a deadline up, which turns the 1750 µs gap
/// before an RTU request into 2 to 3 ms (docs/performance.md, "RTU at the line's
/// limit"). No thread and no spinning: the timerfd wakes the reactor's `epoll_wait`
/// at the instant it is set to.
#[derive(Debug)]
pub struct PreciseTimer {
    fd: tokio::io::unix::AsyncFd<std::os::fd::OwnedFd>,
    /// The instant it is set to go off.
    armed: Option<tokio::time::Instant>,
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
        // SAFETY: an `OwnedFd` keeps its descriptor open, and the same, until it drops,
        // which is when the `AsyncFd` holding it does.
        #[allow(unsafe_code)]
        let fd = unsafe {
            tokio::io::unix::AsyncFd::register_with_interest(owned, tokio::io::Interest::READABLE)
        }?;
        Ok(PreciseTimer { fd, armed: None })
    }

    /// Returns at `at`, or at once if it has passed. Sets the timerfd only when it is
    /// not already set to go off by `at` and after now: a loop that waits for a later
    /// instant each time (a new response deadline each transaction) leaves the earlier
    /// setting, is woken by it once, and only then sets the timerfd again, so a line
    /// polled without pause makes one system call for it each timeout's worth of
    /// transactions, not one each (docs/performance.md "What a transaction costs").
    pub async fn until(&mut self, at: tokio::time::Instant) -> std::io::Result<()> {
        let now = tokio::time::Instant::now();
        if at <= now {
            return Ok(());
        }
        if !self.armed.is_some_and(|a| a > now && a <= at) {
            self.arm(at, now)?;
        }
        loop {
            let mut ready = self.fd.readable().await?;
            // Readiness left over from an earlier setting says nothing about this one:
            // each expiry wakes the reactor anew (edge-triggered), so clearing it and
            // waiting again loses nothing.
            ready.clear_ready();
            let now = tokio::time::Instant::now();
            if now >= at {
                return Ok(());
            }
            // Woken by an earlier setting left in place: now for `at`.
            if self.armed.is_none_or(|a| a <= now) {
                self.arm(at, now)?;
            }
        }
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
                tv_sec: rest.as_secs() as libc::time_t,
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    /// The timer goes off at its instant, not before and not a millisecond after (the
    /// bound is loose for a loaded machine; tokio's timer alone would take the 1750 µs
    /// to 2 or 3 ms, and the median of these is checked against 700 µs); an expiry
    /// nobody waited for does not end a later wait early.
    #[tokio::test]
    async fn precise_timer_is_neither_early_nor_a_tick_late() {
        use tokio::time::Instant;
        let mut timer = PreciseTimer::new().unwrap();
        let mut late = Vec::new();
        for _ in 0..20 {
            let at = Instant::now() + Duration::from_micros(1750);
            timer.until(at).await.unwrap();
            let now = Instant::now();
            assert!(now >= at, "{:?} early", at - now);
            late.push(now - at);
        }
        late.sort();
        assert!(
            late[10] < Duration::from_micros(700),
            "median {:?} late",
            late[10]
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
    }
}
