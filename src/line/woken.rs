//! A future that a busy loop's `select!` can poll at every turn for almost nothing: it
//! is polled itself only when it has woken the task (or is new, or was changed). And
//! the one rule for keeping a task's waker ([`keep`]) that it and the gateway's own
//! channels (`crate::line::outbox`, the relay's commands) share.
//!
//! The relay's and each connection's loop wait on a few futures that seldom finish
//! (shutdown, the idle timer) beside the ones that finish every transaction (bytes
//! read, a command). `select!` polls every branch that is not ready each time the task
//! runs, and polling tokio-util's wait for cancellation locks a mutex, and a tokio
//! `Sleep` goes through the timer's state: together about 4 % of the gateway's
//! instructions a transaction (callgrind, docs/performance.md "Instructions a
//! transaction, counted"). Wrapped in [`Woken`], the inner future is given a waker of
//! its own; the wrapper polls it again only after that waker fired, and otherwise
//! returns `Pending` after comparing the task's waker with the one it passed on.

use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll, Wake, Waker};

/// Keeps `waker` in `slot` unless the one there wakes the same task (a clone, and
/// the store, only when the task's waker changed); true if it was kept anew.
pub(crate) fn keep(slot: &mut Option<Waker>, waker: &Waker) -> bool {
    if slot.as_ref().is_some_and(|w| w.will_wake(waker)) {
        return false;
    }
    *slot = Some(waker.clone());
    true
}

/// `F`, polled only after it woke the task (see the module notes).
pub(crate) struct Woken<F> {
    inner: Pin<Box<F>>,
    signal: Arc<Signal>,
    /// The waker handed to the inner future (wakes `signal`), made once.
    own: Waker,
    /// The task's waker `signal` holds now: registered again only when the task's
    /// waker changes.
    task: Option<Waker>,
    /// Poll the inner future at the next poll whatever the signal says: it is new, or
    /// was changed ([`Woken::inner`]).
    fresh: bool,
}

struct Signal {
    woken: AtomicBool,
    /// The task to wake; locked only when the task's waker changes or the inner
    /// future wakes, never in a poll that finds nothing to do.
    task: Mutex<Option<Waker>>,
}

impl Wake for Signal {
    fn wake(self: Arc<Self>) {
        self.wake_by_ref();
    }

    fn wake_by_ref(self: &Arc<Self>) {
        self.woken.store(true, Ordering::Release);
        let task = self.task.lock().unwrap_or_else(|e| e.into_inner()).clone();
        if let Some(w) = task {
            w.wake();
        }
    }
}

impl<F: Future> Woken<F> {
    pub(crate) fn new(inner: F) -> Self {
        let signal = Arc::new(Signal {
            woken: AtomicBool::new(false),
            task: Mutex::new(None),
        });
        Self {
            inner: Box::pin(inner),
            own: Waker::from(signal.clone()),
            signal,
            task: None,
            fresh: true,
        }
    }

    /// The inner future, to change (a timer reset): it is polled at the next poll, so
    /// it registers its waker afresh.
    pub(crate) fn inner(&mut self) -> Pin<&mut F> {
        self.fresh = true;
        self.inner.as_mut()
    }
}

impl<F: Future> Future for Woken<F> {
    type Output = F::Output;

    fn poll(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<F::Output> {
        // Unpin: the inner future is boxed.
        let this = self.get_mut();
        if keep(&mut this.task, cx.waker()) {
            *this.signal.task.lock().unwrap_or_else(|e| e.into_inner()) = this.task.clone();
        }
        let woken = this.signal.woken.swap(false, Ordering::AcqRel);
        if !(woken || std::mem::take(&mut this.fresh)) {
            return Poll::Pending;
        }
        this.inner
            .as_mut()
            .poll(&mut Context::from_waker(&this.own))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::AtomicUsize;
    use std::time::Duration;

    /// Counts its polls; ready once `open` is set, waking the waker it last saw when
    /// `open` is set through [`Gate::open`].
    #[derive(Default)]
    struct Gate {
        polls: AtomicUsize,
        open: AtomicBool,
        waker: Mutex<Option<Waker>>,
    }

    impl Gate {
        fn open(&self) {
            self.open.store(true, Ordering::Release);
            if let Some(w) = self.waker.lock().unwrap().take() {
                w.wake();
            }
        }
    }

    struct Wait(Arc<Gate>);

    impl Future for Wait {
        type Output = ();
        fn poll(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<()> {
            self.0.polls.fetch_add(1, Ordering::Relaxed);
            if self.0.open.load(Ordering::Acquire) {
                return Poll::Ready(());
            }
            *self.0.waker.lock().unwrap() = Some(cx.waker().clone());
            Poll::Pending
        }
    }

    struct CountWakes(AtomicUsize);
    impl Wake for CountWakes {
        fn wake(self: Arc<Self>) {
            self.0.fetch_add(1, Ordering::Relaxed);
        }
    }

    #[test]
    fn polled_once_until_it_wakes_then_ready() {
        let gate = Arc::new(Gate::default());
        let mut w = Woken::new(Wait(gate.clone()));
        let wakes = Arc::new(CountWakes(AtomicUsize::new(0)));
        let waker = Waker::from(wakes.clone());
        let mut cx = Context::from_waker(&waker);
        for _ in 0..100 {
            assert!(Pin::new(&mut w).poll(&mut cx).is_pending());
        }
        assert_eq!(
            gate.polls.load(Ordering::Relaxed),
            1,
            "polled past its first"
        );
        gate.open();
        assert_eq!(wakes.0.load(Ordering::Relaxed), 1, "the task was not woken");
        assert!(Pin::new(&mut w).poll(&mut cx).is_ready());
        assert_eq!(gate.polls.load(Ordering::Relaxed), 2);
    }

    #[test]
    fn a_new_task_waker_is_the_one_woken() {
        let gate = Arc::new(Gate::default());
        let mut w = Woken::new(Wait(gate.clone()));
        let (first, second) = (
            Arc::new(CountWakes(AtomicUsize::new(0))),
            Arc::new(CountWakes(AtomicUsize::new(0))),
        );
        let waker = Waker::from(first.clone());
        assert!(Pin::new(&mut w)
            .poll(&mut Context::from_waker(&waker))
            .is_pending());
        let waker = Waker::from(second.clone());
        assert!(Pin::new(&mut w)
            .poll(&mut Context::from_waker(&waker))
            .is_pending());
        gate.open();
        assert_eq!(first.0.load(Ordering::Relaxed), 0);
        assert_eq!(second.0.load(Ordering::Relaxed), 1);
    }

    #[tokio::test]
    async fn a_timer_reset_through_inner_still_fires() {
        let start = tokio::time::Instant::now();
        let mut sleep = Woken::new(tokio::time::sleep_until(start + Duration::from_secs(60)));
        // Polled once (registered), then moved earlier: it must fire at the new time,
        // not at the first.
        assert!(futures_poll(&mut sleep).is_pending());
        sleep.inner().reset(start + Duration::from_millis(20));
        tokio::time::timeout(Duration::from_secs(30), &mut sleep)
            .await
            .expect("the timer reset kept its first deadline");
        assert!(start.elapsed() >= Duration::from_millis(20));
    }

    #[tokio::test]
    async fn a_cancellation_reaches_the_loop() {
        let token = tokio_util::sync::CancellationToken::new();
        let mut wait = Woken::new(token.clone().cancelled_owned());
        let t = token.clone();
        tokio::spawn(async move {
            tokio::time::sleep(Duration::from_millis(20)).await;
            t.cancel();
        });
        let mut turns = 0u32;
        loop {
            tokio::select! {
                _ = &mut wait => break,
                _ = tokio::time::sleep(Duration::from_millis(1)) => turns += 1,
            }
            assert!(turns < 10_000, "never woken");
        }
        assert!(token.is_cancelled());
    }

    /// One poll of `f` with a waker that does nothing.
    fn futures_poll<F: Future + Unpin>(f: &mut F) -> Poll<F::Output> {
        Pin::new(f).poll(&mut Context::from_waker(Waker::noop()))
    }
}
