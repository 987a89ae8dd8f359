//! Which line a request goes to, by its unit id (docs/design.md §4.1): each line's
//! relay is its own task, with its own queue, timeouts and backoff, so a dead line
//! never holds up another. A unit no line serves is answered 0x0A at once; a
//! remapped unit goes down its line under the line's id and comes back under the
//! master's.

use crate::config::LineConfig;
use crate::frame::Adu;
use crate::line::outbox::{Notifier, Refusal, Ticket};
use crate::line::relay::{Command, ConnId, RelayHandle};
use crate::ops::stats::Stats;

/// The relays of every line, and the route of each unit id.
#[derive(Debug, Clone)]
pub(crate) struct Router {
    relays: Vec<RelayHandle>,
    /// For each unit id the master may ask: its line and its id on that line.
    routes: Vec<Option<(usize, u8)>>,
}

/// Why a request was answered here and not by a line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Unrouted {
    /// No line serves the unit.
    NoLine,
    /// Its line's relay has stopped (shutting down).
    Stopped,
}

impl Router {
    /// `relays[i]` runs `lines[i]`.
    pub(crate) fn new(lines: &[LineConfig], relays: Vec<RelayHandle>) -> Router {
        let routes = (0..=255u8)
            .map(|unit| {
                // A line that lists units (or remaps them) before one that serves
                // every unit: that is only ever the one line of the old form.
                let listed = lines.iter().enumerate().filter(|(_, l)| !l.units.every());
                let every = lines.iter().enumerate().filter(|(_, l)| l.units.every());
                listed
                    .chain(every)
                    .find_map(|(i, l)| l.units.route(unit).map(|on_line| (i, on_line)))
            })
            .collect();
        Router { relays, routes }
    }

    /// A master connected: every line may send it notifications.
    pub(crate) fn attach(&self, conn: ConnId, notifier: &Notifier) -> bool {
        let mut attached = false;
        for relay in &self.relays {
            let cmd = Command::Attach {
                conn,
                notifier: notifier.clone(),
            };
            attached |= relay.send(cmd).is_ok();
        }
        attached
    }

    /// The master's priority class on every line (docs/masters.md "Priority"); 0,
    /// the default, needs no word.
    pub(crate) fn classify(&self, conn: ConnId, class: u8) {
        if class == 0 {
            return;
        }
        for relay in &self.relays {
            let _ = relay.send(Command::Priority { conn, class });
        }
    }

    /// It went away: every line drops its queued requests.
    pub(crate) fn detach(&self, conn: ConnId) {
        for relay in &self.relays {
            let _ = relay.send(Command::Detach { conn });
        }
    }

    /// Hands the request to the line serving its unit, under the line's id for it;
    /// else answers 0x0A through its ticket (counted in `stats`) and says why.
    pub(crate) fn submit(
        &self,
        conn: ConnId,
        adu: Adu,
        ticket: Ticket,
        stats: &Stats,
    ) -> Result<(), Unrouted> {
        let unit = adu.unit();
        let Some((line, on_line)) = self.routes[usize::from(unit)] else {
            ticket.refuse(&adu, Refusal::Unavailable, stats);
            return Err(Unrouted::NoLine);
        };
        let (adu, ticket) = if on_line == unit {
            (adu, ticket)
        } else {
            let remapped = Adu::build(adu.tid(), on_line, adu.pdu());
            (remapped, ticket.answering_as(unit))
        };
        let cmd = Command::Request { conn, adu, ticket };
        if let Err(Command::Request { adu, ticket, .. }) = self.relays[line].send(cmd) {
            ticket.refuse(&adu, Refusal::Unavailable, stats);
            return Err(Unrouted::Stopped);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Units;
    use crate::line::outbox::Outbox;

    fn line(ids: &[u8], remap: &[(u8, u8)]) -> LineConfig {
        LineConfig {
            units: Units {
                ids: ids.iter().copied().collect(),
                remap: remap.iter().copied().collect(),
            },
            ..LineConfig::default()
        }
    }

    /// Units go to the line that lists them, remapped ones under the line's id and
    /// answered under the master's; a unit on no line is answered 0x0A at once.
    #[tokio::test]
    async fn routes_by_unit_remaps_and_answers_unrouted_units_0x0a() {
        let lines = [line(&[1, 2], &[]), line(&[3], &[(11, 1)])];
        let (tx0, mut rx0) = crate::line::relay::channel();
        let (tx1, mut rx1) = crate::line::relay::channel();
        let router = Router::new(&lines, vec![tx0, tx1]);
        let (mut outbox, mut inbox) = Outbox::new(4);
        let read = |tid, unit| Adu::build(tid, unit, &[3, 0, 0, 0, 1]);

        router
            .submit(1, read(1, 2), outbox.ticket().await, &Stats::default())
            .unwrap();
        let Some(Command::Request { adu, .. }) = rx0.recv().await else {
            panic!("unit 2 goes to the first line")
        };
        assert_eq!(adu.as_bytes(), read(1, 2).as_bytes());

        router
            .submit(1, read(2, 11), outbox.ticket().await, &Stats::default())
            .unwrap();
        let Some(Command::Request { adu, ticket, .. }) = rx1.recv().await else {
            panic!("unit 11 goes to the second line")
        };
        assert_eq!(adu.unit(), 1, "as unit 1 on that line");
        let e = router.submit(1, read(3, 4), outbox.ticket().await, &Stats::default());
        assert_eq!(e, Err(Unrouted::NoLine));

        // The first request is never answered (dropped); the second is, as unit 1.
        ticket.answer(Adu::build(2, 1, &[3, 2, 0, 7]));
        let second = inbox.next().await.unwrap();
        assert_eq!(
            second.adu().as_bytes(),
            Adu::build(2, 11, &[3, 2, 0, 7]).as_bytes()
        );
        let third = inbox.next().await.unwrap();
        assert_eq!(
            third.adu().as_bytes(),
            Adu::exception(3, 4, 3, 0x0A).as_bytes()
        );
        assert!(rx0.try_recv().is_none() && rx1.try_recv().is_none());
    }

    /// The one line of the old form serves every unit, 0 included.
    #[test]
    fn one_line_without_units_serves_every_unit() {
        let (tx, _rx) = crate::line::relay::channel();
        let router = Router::new(&[LineConfig::default()], vec![tx]);
        assert!((0..=255u8).all(|u| router.routes[usize::from(u)] == Some((0, u))));
    }
}
