//! What connections tell the relay, and the channel they tell it through: a queue
//! under a mutex with the relay's waker beside it, one uncontended lock a command
//! (tokio's unbounded channel took about 400 instructions a transaction for the
//! same: callgrind, docs/performance.md "Instructions a transaction, counted").

use crate::config::RelayConfig;
use crate::frame::Adu;
use crate::outbox::{Notifier, Ticket};
use crate::woken::keep;
use std::collections::VecDeque;
use std::future::poll_fn;
use std::sync::{Arc, Mutex, MutexGuard};
use std::task::{Poll, Waker};

/// Identifies one master's TCP connection.
pub type ConnId = u64;

/// What connections tell the relay.
#[derive(Debug)]
pub enum Command {
    /// A master connected; notifications reach it through `notifier`.
    Attach {
        /// The connection.
        conn: ConnId,
        /// Where notifications for it go.
        notifier: Notifier,
    },
    /// It went away: its queued requests are dropped, its late replies discarded.
    Detach {
        /// The connection gone.
        conn: ConnId,
    },
    /// A request that passed the strict checks, with the master's own transaction id;
    /// its answer goes back through `ticket`, in the master's order.
    Request {
        /// The connection it came on.
        conn: ConnId,
        /// The request as the master framed it.
        adu: Adu,
        /// Its place in the master's reply order.
        ticket: Ticket,
    },
    /// The master's priority class on this line from now on (docs/masters.md
    /// "Priority").
    Priority {
        /// The master.
        conn: ConnId,
        /// 0 (the default, the lowest) to 7.
        class: u8,
    },
    /// A reload (SIGHUP): the response and probe timeouts, retries and the traffic log
    /// from now on; requests already on the line keep their deadlines.
    Retune {
        /// The line's new `[relay]` settings.
        relay: Box<RelayConfig>,
        /// The line's `[[line.unit]]` tables.
        units: crate::config::unit::UnitTables,
        /// Log every frame as hex (`log.traffic`).
        traffic: bool,
    },
}

/// The relay's channel: the handle connections send through, and the relay's end.
pub(crate) fn channel() -> (RelayHandle, Commands) {
    let shared = Arc::new(Channel {
        state: Mutex::new(State {
            queue: VecDeque::new(),
            senders: 1,
            open: true,
            relay: None,
        }),
    });
    (
        RelayHandle {
            shared: shared.clone(),
        },
        Commands { shared },
    )
}

struct Channel {
    state: Mutex<State>,
}

struct State {
    queue: VecDeque<Command>,
    /// Handles alive: none left and the queue empty, the relay hears nothing more.
    senders: usize,
    /// The relay's end is still there.
    open: bool,
    /// The relay, waiting for a command.
    relay: Option<Waker>,
}

impl Channel {
    fn lock(&self) -> MutexGuard<'_, State> {
        // Nothing panics while holding it.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// The connections' side of the relay's channel.
pub struct RelayHandle {
    shared: Arc<Channel>,
}

impl RelayHandle {
    /// Sends a command; gives it back if the relay has stopped.
    pub fn send(&self, cmd: Command) -> Result<(), Command> {
        let relay = {
            let mut s = self.shared.lock();
            if !s.open {
                return Err(cmd);
            }
            s.queue.push_back(cmd);
            s.relay.take()
        };
        if let Some(w) = relay {
            w.wake();
        }
        Ok(())
    }
}

impl Clone for RelayHandle {
    fn clone(&self) -> Self {
        self.shared.lock().senders += 1;
        RelayHandle {
            shared: self.shared.clone(),
        }
    }
}

impl Drop for RelayHandle {
    fn drop(&mut self) {
        let relay = {
            let mut s = self.shared.lock();
            s.senders -= 1;
            if s.senders == 0 {
                s.relay.take()
            } else {
                None
            }
        };
        if let Some(w) = relay {
            w.wake();
        }
    }
}

impl std::fmt::Debug for RelayHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("RelayHandle")
    }
}

/// The relay's end of its channel.
pub(crate) struct Commands {
    shared: Arc<Channel>,
}

impl Commands {
    /// The next command, in the order sent; `None` once none is left and every
    /// handle is gone. Cancel-safe: nothing is taken unless returned.
    pub(crate) async fn recv(&mut self) -> Option<Command> {
        poll_fn(|cx| {
            let mut s = self.shared.lock();
            if let Some(cmd) = s.queue.pop_front() {
                return Poll::Ready(Some(cmd));
            }
            if s.senders == 0 {
                return Poll::Ready(None);
            }
            keep(&mut s.relay, cx.waker());
            Poll::Pending
        })
        .await
    }

    /// The next command if one is waiting (tests).
    #[cfg(test)]
    pub(crate) fn try_recv(&mut self) -> Option<Command> {
        self.shared.lock().queue.pop_front()
    }
}

impl Drop for Commands {
    fn drop(&mut self) {
        let unsent = {
            let mut s = self.shared.lock();
            s.open = false;
            std::mem::take(&mut s.queue)
        };
        // Their tickets answer "no reply" as they drop, outside the lock.
        drop(unsent);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[tokio::test]
    async fn commands_in_order_then_none_once_every_handle_is_gone() {
        let (handle, mut commands) = channel();
        let second = handle.clone();
        handle.send(Command::Detach { conn: 1 }).unwrap();
        second.send(Command::Detach { conn: 2 }).unwrap();
        let relay = tokio::spawn(async move {
            let mut got = Vec::new();
            while let Some(Command::Detach { conn }) = commands.recv().await {
                got.push(conn);
            }
            got
        });
        tokio::task::yield_now().await;
        // Sent while the relay waits: it is woken for it.
        second.send(Command::Detach { conn: 3 }).unwrap();
        drop((handle, second));
        let got = tokio::time::timeout(Duration::from_secs(1), relay)
            .await
            .expect("the relay heard the end")
            .unwrap();
        assert_eq!(got, [1, 2, 3]);
    }

    #[test]
    fn a_stopped_relay_gives_the_command_back() {
        let (handle, commands) = channel();
        drop(commands);
        let back = handle.send(Command::Detach { conn: 7 });
        assert!(matches!(back, Err(Command::Detach { conn: 7 })));
    }
}
