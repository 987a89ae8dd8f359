//! What connections tell the relay, and the channel they tell it through
//! (`outbox/queue.rs`: one uncontended lock a command; tokio's unbounded channel took
//! about 400 instructions a transaction for the same: callgrind, docs/performance.md
//! "Instructions a transaction, counted").

use crate::config::RelayConfig;
use crate::frame::Adu;
use crate::line::outbox::queue::{self, Receiver, Sender};
use crate::line::outbox::{Notifier, Ticket};

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
    let (tx, rx) = queue::channel(());
    (RelayHandle(tx), Commands(rx))
}

/// The connections' side of the relay's channel.
#[derive(Clone)]
pub struct RelayHandle(Sender<Command, ()>);

impl RelayHandle {
    /// Sends a command; gives it back if the relay has stopped.
    pub fn send(&self, cmd: Command) -> Result<(), Command> {
        self.0.send_if(cmd, |_| true)
    }
}

impl std::fmt::Debug for RelayHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("RelayHandle")
    }
}

/// The relay's end of its channel. Dropped, it drops the commands left: their
/// tickets answer "no reply" as they drop.
pub(crate) struct Commands(Receiver<Command, ()>);

impl Commands {
    /// The next command, in the order sent; `None` once none is left and every
    /// handle is gone. Cancel-safe: nothing is taken unless returned. (Tests: the
    /// relay polls, [`Commands::poll_recv`].)
    #[cfg(test)]
    pub(crate) fn recv(&mut self) -> impl std::future::Future<Output = Option<Command>> + '_ {
        self.0.recv()
    }

    /// [`Commands::recv`] as a poll (the relay's wait, `event.rs`).
    pub(crate) fn poll_recv(
        &mut self,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Option<Command>> {
        self.0.poll_recv(cx)
    }

    /// The next command if one is waiting (tests).
    #[cfg(test)]
    pub(crate) fn try_recv(&mut self) -> Option<Command> {
        self.0.try_recv()
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
