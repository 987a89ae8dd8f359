//! What connections tell the relay, and the handle they tell it through.

use crate::config::RelayConfig;
use crate::frame::Adu;
use crate::outbox::{Notifier, Ticket};
use tokio::sync::mpsc;

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

/// The connections' side of the relay's channel.
#[derive(Debug, Clone)]
pub struct RelayHandle {
    tx: mpsc::UnboundedSender<Command>,
}

impl RelayHandle {
    pub(crate) fn new(tx: mpsc::UnboundedSender<Command>) -> Self {
        Self { tx }
    }

    /// Sends a command; gives it back if the relay has stopped.
    pub fn send(&self, cmd: Command) -> Result<(), Command> {
        self.tx.send(cmd).map_err(|e| e.0)
    }
}
