//! The channel under each master's way back (`outbox.rs`) and the relay's commands
//! (`relay/command.rs`): a queue under one mutex, the receiver's waker beside it, and
//! a count of the senders alive, so that the receiver hears the end once the last is
//! gone. One uncontended lock an item: tokio's channels took hundreds of
//! instructions more a transaction for the same (docs/performance.md "Instructions a
//! transaction, counted").
//!
//! The invariant, kept here and nowhere else: `senders` is the number of [`Sender`]s
//! alive. The channel starts with one; a clone adds one under the lock; a drop, or
//! [`Sender::send_and_leave`], takes one off under the lock, and whoever takes the
//! count to 0 wakes the receiver. So [`Receiver::recv`] returns `None` only once the
//! queue is empty and no sender is left, never before the last item sent, and a
//! receiver waiting then is always woken. Every waker is woken after the lock is
//! released, and the items the receiver never took are dropped after it (an item may
//! lock the state as it drops: a reply's pipelining slot does). Nothing panics while
//! the lock is held, so a poisoned lock is taken as it is: each count changes in one
//! statement and is whole.

use crate::line::woken::keep;
use std::collections::VecDeque;
use std::future::{poll_fn, Future};
use std::sync::{Arc, Mutex, MutexGuard};
use std::task::{Context, Poll, Waker};

/// What a user of the channel keeps beside the queue, under the same lock.
pub(crate) trait Beside {
    /// The receiver took an item, or went away (under the lock): the waker of a task
    /// waiting for room, to be woken once the lock is released.
    fn room(&mut self) -> Option<Waker> {
        None
    }
}

impl Beside for () {}

/// A channel: its first sender, and its receiver; `more` kept beside the queue.
pub(crate) fn channel<T, X: Beside>(more: X) -> (Sender<T, X>, Receiver<T, X>) {
    let shared = Arc::new(SharedQueue {
        state: Mutex::new(QueueState {
            items: VecDeque::new(),
            senders: 1,
            open: true,
            receiver: None,
            more,
        }),
    });
    let sender = Sender {
        shared: Some(shared.clone()),
    };
    (sender, Receiver { shared })
}

/// The state both ends share.
pub(crate) struct SharedQueue<T, X> {
    state: Mutex<QueueState<T, X>>,
}

impl<T, X> SharedQueue<T, X> {
    /// The state, locked.
    pub(crate) fn lock(&self) -> MutexGuard<'_, QueueState<T, X>> {
        // Nothing panics while holding it (the module notes).
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// The queue, its counts, and what its user keeps beside it.
pub(crate) struct QueueState<T, X> {
    /// Sent and not yet taken, in the order sent.
    items: VecDeque<T>,
    /// Senders alive (the module notes).
    senders: usize,
    /// The receiver is still there; once it is gone, nothing more is queued.
    open: bool,
    /// The receiver, waiting for an item.
    receiver: Option<Waker>,
    /// The user's own state, under the same lock.
    pub(crate) more: X,
}

impl<T, X> QueueState<T, X> {
    /// Items sent and not yet taken.
    pub(crate) fn len(&self) -> usize {
        self.items.len()
    }

    /// Queues `item` unless the receiver is gone: the receiver's waker, to wake once
    /// the lock is released.
    fn push(&mut self, item: T) -> Result<Option<Waker>, T> {
        if !self.open {
            return Err(item);
        }
        self.items.push_back(item);
        Ok(self.receiver.take())
    }
}

/// Wakes `waker`, if any (after the lock).
fn wake(waker: Option<Waker>) {
    if let Some(w) = waker {
        w.wake();
    }
}

/// One end that may send. Dropping it is its leaving.
pub(crate) struct Sender<T, X> {
    /// Always there but in `send_and_leave`, which leaves the count as it goes.
    shared: Option<Arc<SharedQueue<T, X>>>,
}

impl<T, X> Sender<T, X> {
    /// The state both ends share (a reply's slot keeps it).
    pub(crate) fn shared(&self) -> &Arc<SharedQueue<T, X>> {
        self.shared.as_ref().expect("there until it leaves")
    }

    /// The state, locked.
    pub(crate) fn lock(&self) -> MutexGuard<'_, QueueState<T, X>> {
        self.shared().lock()
    }

    /// Queues `item` if the receiver is there and `room` says so (under the lock);
    /// else gives it back.
    pub(crate) fn send_if(
        &self,
        item: T,
        room: impl FnOnce(&QueueState<T, X>) -> bool,
    ) -> Result<(), T> {
        let receiver = {
            let mut s = self.lock();
            if !room(&s) {
                return Err(item);
            }
            s.push(item)?
        };
        wake(receiver);
        Ok(())
    }

    /// Queues `item` and leaves, in one lock, after `also`; gives the item back, to be
    /// dropped after the lock, if the receiver is gone.
    pub(crate) fn send_and_leave(mut self, item: T, also: impl FnOnce(&mut X)) -> Result<(), T> {
        let shared = self.shared.take().expect("there until it leaves");
        let receiver = {
            let mut s = shared.lock();
            also(&mut s.more);
            s.senders -= 1;
            s.push(item)?
        };
        wake(receiver);
        Ok(())
    }

    /// Another sender, counted under the lock `s` its caller holds: `s` must be this
    /// channel's.
    pub(crate) fn clone_locked(&self, s: &mut QueueState<T, X>) -> Self {
        s.senders += 1;
        Sender {
            shared: self.shared.clone(),
        }
    }
}

impl<T, X> Clone for Sender<T, X> {
    fn clone(&self) -> Self {
        self.clone_locked(&mut self.lock())
    }
}

impl<T, X> Drop for Sender<T, X> {
    fn drop(&mut self) {
        let Some(shared) = self.shared.take() else {
            return;
        };
        let receiver = {
            let mut s = shared.lock();
            s.senders -= 1;
            match s.senders {
                0 => s.receiver.take(),
                _ => None,
            }
        };
        wake(receiver);
    }
}

/// The receiving end. Dropping it closes the channel: what was sent and not taken is
/// dropped, and nothing more is queued.
pub(crate) struct Receiver<T, X: Beside> {
    shared: Arc<SharedQueue<T, X>>,
}

impl<T, X: Beside> Receiver<T, X> {
    /// The next item, in the order sent; `None` once none is left and no sender is.
    /// Cancel-safe: nothing is taken unless returned. The future itself, not an `async
    /// fn`, and so are its callers' (`Commands::recv`, `Inbox`'s): no state machine
    /// wrapped around another is polled on the way to the lock (with them, about 90
    /// instructions more a transaction, `scripts/instructions`).
    pub(crate) fn recv(&mut self) -> impl Future<Output = Option<T>> + '_ {
        poll_fn(|cx| self.poll_recv(cx))
    }

    /// [`Receiver::recv`] as a poll, for a loop that polls its sources itself.
    pub(crate) fn poll_recv(&mut self, cx: &mut Context<'_>) -> Poll<Option<T>> {
        let mut s = self.shared.lock();
        if let Some(item) = s.items.pop_front() {
            let waiting = s.more.room();
            drop(s);
            wake(waiting);
            return Poll::Ready(Some(item));
        }
        if s.senders == 0 {
            return Poll::Ready(None);
        }
        keep(&mut s.receiver, cx.waker());
        Poll::Pending
    }

    /// The next item if one is waiting (tests).
    #[cfg(test)]
    pub(crate) fn try_recv(&mut self) -> Option<T> {
        self.shared.lock().items.pop_front()
    }
}

impl<T, X: Beside> Drop for Receiver<T, X> {
    fn drop(&mut self) {
        let (unsent, waiting) = {
            let mut s = self.shared.lock();
            s.open = false;
            (std::mem::take(&mut s.items), s.more.room())
        };
        // Outside the lock: an item may lock it as it drops.
        drop(unsent);
        wake(waiting);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[tokio::test]
    async fn items_in_order_then_none_once_every_sender_is_gone() {
        let (first, mut rx) = channel::<u32, ()>(());
        let second = first.clone();
        first.send_if(1, |_| true).unwrap();
        second.send_if(2, |_| true).unwrap();
        let receiver = tokio::spawn(async move {
            let mut got = Vec::new();
            while let Some(n) = rx.recv().await {
                got.push(n);
            }
            got
        });
        tokio::task::yield_now().await;
        // Sent while the receiver waits, by a sender that leaves with it: it is woken
        // for it, and then hears the end once the other is dropped.
        second.send_and_leave(3, |_| {}).unwrap();
        tokio::task::yield_now().await;
        // The receiver took it and waits again: the last sender's drop wakes it.
        drop(first);
        let got = tokio::time::timeout(Duration::from_secs(1), receiver)
            .await
            .expect("the receiver heard the end")
            .unwrap();
        assert_eq!(got, [1, 2, 3]);
    }

    #[test]
    fn a_closed_channel_gives_the_item_back_and_room_decides() {
        let (tx, rx) = channel::<u32, ()>(());
        assert_eq!(tx.send_if(5, |s| s.len() < 1), Ok(()));
        assert_eq!(tx.send_if(6, |s| s.len() < 1), Err(6));
        drop(rx);
        assert_eq!(tx.send_if(7, |_| true), Err(7));
        assert_eq!(tx.clone().send_and_leave(8, |_| {}), Err(8));
    }

    /// Beside the queue: how many times the receiver made room.
    #[derive(Default)]
    struct Rooms(u32);

    impl Beside for Rooms {
        fn room(&mut self) -> Option<Waker> {
            self.0 += 1;
            None
        }
    }

    /// An item that locks the state as it drops, as a reply's slot does.
    struct Locks(Arc<SharedQueue<Locks, Rooms>>);

    impl Drop for Locks {
        fn drop(&mut self) {
            self.0.lock().more.0 += 10;
        }
    }

    #[tokio::test]
    async fn items_never_taken_drop_after_the_lock_and_counts_stay_whole() {
        let (tx, mut rx) = channel::<Locks, Rooms>(Rooms::default());
        let shared = tx.shared().clone();
        for _ in 0..3 {
            let mut s = tx.lock();
            let extra = tx.clone_locked(&mut s);
            drop(s);
            extra
                .send_and_leave(Locks(shared.clone()), |r| r.0 += 100)
                .map_err(|_| "closed")
                .unwrap();
        }
        // One taken (room made once, the item dropped here: 10), two left to the
        // closing receiver (room made once more, each dropped outside the lock).
        drop(rx.recv().await);
        drop(rx);
        let s = shared.lock();
        assert_eq!((s.more.0, s.senders, s.open), (300 + 2 + 30, 1, false));
    }
}
