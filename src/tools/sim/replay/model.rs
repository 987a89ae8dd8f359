//! The replayed devices' model (pure): for each unit, every register and bit it was
//! seen to hold and when, the latest outcome of each distinct request (a reply, an
//! exception, silence), the exception it gave to writes, and its reply times
//! (docs/simulator.md "Replaying a device"). Built by applying observations in time
//! order, so where captures disagree the latest wins.

use super::learn::{Observation, RecordedReply};
use crate::config::Framing;
use std::collections::{BTreeMap, HashMap};

/// The four tables, as the read functions number them (FC 01 to 04).
pub(crate) const TABLES: [&str; 4] = [
    "coils",
    "discrete inputs",
    "holding registers",
    "input registers",
];

/// One address's values over the capture, and what a master wrote during the replay.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(crate) struct Cell {
    /// (when, value), in time order.
    pub(crate) history: Vec<(u64, u16)>,
    /// Written during the replay: wins over the history from then on.
    pub(crate) written: Option<u16>,
}

impl Cell {
    /// The value at `moment` (µs since the epoch, in the capture's time): the last
    /// recorded at or before it, else the first. `None` for the latest.
    pub(crate) fn value(&self, moment: Option<u64>) -> Option<u16> {
        if let Some(w) = self.written {
            return Some(w);
        }
        match moment {
            None => self.history.last().map(|&(_, v)| v),
            Some(t) => {
                let n = self.history.partition_point(|&(at, _)| at <= t);
                self.history.get(n.saturating_sub(1)).map(|&(_, v)| v)
            }
        }
    }

    fn record(&mut self, at: u64, value: u16) {
        // Observations come in time order; one from another file may be older.
        let n = self.history.partition_point(|&(t, _)| t <= at);
        self.history.insert(n, (at, value));
    }
}

/// What a unit did with one distinct request PDU, the latest time it was asked.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum ReplayOutcome {
    /// Its reply (a normal response).
    Reply(Vec<u8>),
    /// An exception response with this code.
    Exception(u8),
    /// No answer.
    Silent,
}

/// One device, by unit id.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(crate) struct Unit {
    /// Coils, discrete inputs, holding and input registers, by address.
    pub(crate) tables: [BTreeMap<u16, Cell>; 4],
    /// By request PDU: (when, what came of it).
    pub(crate) outcomes: HashMap<Vec<u8>, (u64, ReplayOutcome)>,
    /// The latest exception it gave to a write (FC 05, 06, 0F, 10, 16, 17), and when.
    pub(crate) write_exception: Option<(u64, u8)>,
    /// Request out to reply in, µs, sorted (as recorded, for the summary).
    pub(crate) turnarounds_us: Vec<u64>,
    /// The device's own times of those (less the wire's: `learn::own_times`), µs,
    /// in the order recorded: the replay's delays are drawn from them.
    pub(crate) own_us: Vec<u64>,
    /// The same, request by request (a device takes longer for some).
    pub(crate) own_by_request: HashMap<Vec<u8>, Vec<u64>>,
    /// How its line carried it.
    pub(crate) framing: Option<Framing>,
}

/// Every replayed unit, and the capture's first moment (the timeline's start).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(crate) struct Model {
    pub(crate) units: BTreeMap<u8, Unit>,
    pub(crate) start_us: Option<u64>,
    pub(crate) end_us: Option<u64>,
}

fn word(pdu: &[u8], at: usize) -> Option<u16> {
    Some(u16::from_be_bytes([*pdu.get(at)?, *pdu.get(at + 1)?]))
}

/// The bits of `data` (packed, first bit lowest), `count` of them.
fn bits(data: &[u8], count: u16) -> impl Iterator<Item = u16> + '_ {
    (0..usize::from(count)).map(move |i| u16::from(data[i / 8] >> (i % 8) & 1))
}

pub(crate) fn is_write(function: u8) -> bool {
    matches!(function, 0x05 | 0x06 | 0x0F | 0x10 | 0x16 | 0x17)
}

impl Unit {
    /// Values a master put at `table` (0 coils, 2 holding registers) with the write
    /// request `pdu`, as (address, value); empty when the request is malformed.
    pub(crate) fn written_by(pdu: &[u8]) -> Option<(usize, Vec<(u16, u16)>)> {
        let (addr, n) = (word(pdu, 1)?, word(pdu, 3)?);
        let values = match pdu[0] {
            0x05 => (0, vec![(addr, u16::from(n == 0xFF00))]),
            0x06 => (2, vec![(addr, n)]),
            0x0F => {
                let data = pdu.get(6..6 + usize::from(n).div_ceil(8))?;
                let vs = bits(data, n).enumerate();
                (
                    0,
                    vs.map(|(i, v)| (addr.wrapping_add(i as u16), v)).collect(),
                )
            }
            0x10 => {
                let data = pdu.get(6..6 + 2 * usize::from(n))?;
                let vs = data.chunks(2).enumerate();
                let vs = vs.map(|(i, c)| {
                    (
                        addr.wrapping_add(i as u16),
                        u16::from_be_bytes([c[0], c[1]]),
                    )
                });
                (2, vs.collect())
            }
            _ => return None,
        };
        Some(values)
    }

    /// What a normal reply to a read says about the table it read.
    fn learn_read(&mut self, at: u64, request: &[u8], reply: &[u8]) {
        let (Some(addr), Some(n)) = (word(request, 1), word(request, 3)) else {
            return;
        };
        let table = usize::from(request[0] - 1);
        let data = reply.get(2..).unwrap_or(&[]);
        let values: Vec<u16> = match request[0] {
            1 | 2 if data.len() == usize::from(n).div_ceil(8) => bits(data, n).collect(),
            3 | 4 if data.len() == 2 * usize::from(n) => data
                .chunks(2)
                .map(|c| u16::from_be_bytes([c[0], c[1]]))
                .collect(),
            _ => return,
        };
        for (i, v) in values.into_iter().enumerate() {
            let a = addr.wrapping_add(i as u16);
            self.tables[table].entry(a).or_default().record(at, v);
        }
    }

    /// How much of each table is known, as ranges: `holding registers 0-19, 100`.
    pub(crate) fn known(&self) -> Vec<String> {
        let mut out = Vec::new();
        for (name, table) in TABLES.iter().zip(&self.tables) {
            if table.is_empty() {
                continue;
            }
            let mut ranges: Vec<(u16, u16)> = Vec::new();
            for &a in table.keys() {
                match ranges.last_mut() {
                    Some((_, end)) if end.checked_add(1) == Some(a) => *end = a,
                    _ => ranges.push((a, a)),
                }
            }
            let text: Vec<String> = ranges
                .iter()
                .map(|&(s, e)| {
                    if s == e {
                        s.to_string()
                    } else {
                        format!("{s}-{e}")
                    }
                })
                .collect();
            out.push(format!("{} {} ({})", name, text.join(", "), table.len()));
        }
        out
    }

    /// The reply time at quantile `q` (0..1), µs.
    pub(crate) fn quantile_us(&self, q: f64) -> Option<u64> {
        let n = self.turnarounds_us.len();
        let i = ((n as f64 - 1.0) * q).round() as usize;
        self.turnarounds_us.get(i).copied()
    }
}

impl Model {
    /// Applies what one request showed. Observations are applied in time order (of
    /// every file together), so the latest wins.
    pub(crate) fn apply(&mut self, o: &Observation) {
        let Some(&function) = o.request.first() else {
            return;
        };
        self.start_us = Some(self.start_us.map_or(o.at_us, |s| s.min(o.at_us)));
        self.end_us = Some(self.end_us.map_or(o.at_us, |e| e.max(o.at_us)));
        let unit = self.units.entry(o.unit).or_default();
        unit.framing.get_or_insert(o.framing);
        let outcome = match &o.seen {
            RecordedReply::Silent => ReplayOutcome::Silent,
            RecordedReply::Reply(pdu) if pdu.first().is_some_and(|f| f & 0x80 != 0) => {
                let code = pdu.get(1).copied().unwrap_or(0);
                if is_write(function) {
                    unit.write_exception = Some((o.at_us, code));
                }
                ReplayOutcome::Exception(code)
            }
            RecordedReply::Reply(pdu) => {
                match function {
                    1..=4 => unit.learn_read(o.at_us, &o.request, pdu),
                    _ => {
                        if let Some((table, values)) = Unit::written_by(&o.request) {
                            for (a, v) in values {
                                unit.tables[table].entry(a).or_default().record(o.at_us, v);
                            }
                        }
                    }
                }
                ReplayOutcome::Reply(pdu.clone())
            }
        };
        if let Some(t) = o.turnaround_us {
            let n = unit.turnarounds_us.partition_point(|&x| x <= t);
            unit.turnarounds_us.insert(n, t);
            let own = o.own_us.unwrap_or(t);
            unit.own_us.push(own);
            unit.own_by_request
                .entry(o.request.clone())
                .or_default()
                .push(own);
        }
        match unit.outcomes.get(&o.request) {
            Some((at, _)) if *at > o.at_us => {}
            _ => {
                unit.outcomes.insert(o.request.clone(), (o.at_us, outcome));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn seen(at_us: u64, unit: u8, request: &[u8], reply: Option<&[u8]>) -> Observation {
        Observation {
            at_us,
            unit,
            request: request.to_vec(),
            seen: reply.map_or(RecordedReply::Silent, |r| RecordedReply::Reply(r.to_vec())),
            turnaround_us: reply.map(|_| at_us % 1000),
            own_us: reply.map(|_| at_us % 1000),
            framing: Framing::Rtu,
        }
    }

    #[test]
    fn reads_writes_and_exceptions_make_the_model_the_latest_winning() {
        let mut m = Model::default();
        m.apply(&seen(2000, 1, &[3, 0, 10, 0, 2], Some(&[3, 4, 0, 7, 0, 8])));
        // An older capture, applied after: its value is history, not the latest.
        m.apply(&seen(1000, 1, &[3, 0, 10, 0, 1], Some(&[3, 2, 0, 5])));
        m.apply(&seen(
            3000,
            1,
            &[1, 0, 0, 0, 10],
            Some(&[1, 2, 0b0000_0101, 0b10]),
        ));
        m.apply(&seen(4000, 1, &[6, 0, 11, 0, 9], Some(&[6, 0, 11, 0, 9])));
        m.apply(&seen(5000, 1, &[6, 0, 99, 0, 9], Some(&[0x86, 2])));
        m.apply(&seen(6000, 2, &[4, 0, 0, 0, 1], None));
        let u = &m.units[&1];
        let holding = &u.tables[2];
        assert_eq!(holding[&10].value(None), Some(7));
        assert_eq!(holding[&10].value(Some(1500)), Some(5));
        assert_eq!(holding[&11].value(None), Some(9), "the write");
        assert_eq!(holding[&11].value(Some(2500)), Some(8));
        let coils: Vec<_> = (0..10)
            .map(|a| u.tables[0][&a].value(None).unwrap())
            .collect();
        assert_eq!(coils, [1, 0, 1, 0, 0, 0, 0, 0, 0, 1]);
        assert_eq!(u.write_exception, Some((5000, 2)));
        assert_eq!(
            u.outcomes[&vec![6, 0, 99, 0, 9]].1,
            ReplayOutcome::Exception(2)
        );
        assert_eq!(
            m.units[&2].outcomes[&vec![4, 0, 0, 0, 1]].1,
            ReplayOutcome::Silent
        );
        assert_eq!(u.known(), ["coils 0-9 (10)", "holding registers 10-11 (2)"]);
        assert_eq!(u.turnarounds_us, [0, 0, 0, 0, 0]);
        assert_eq!((m.start_us, m.end_us), (Some(1000), Some(6000)));
    }

    /// The summary tells the reply times as recorded; the delays are drawn from the
    /// device's own (the wire's time taken out), request by request.
    #[test]
    fn reply_times_as_recorded_delays_from_the_device_s_own() {
        let mut m = Model::default();
        let (a, b): (&[u8], &[u8]) = (&[3, 0, 0, 0, 1], &[3, 0, 5, 0, 1]);
        for (at, q, turnaround, own) in [(1, a, 9000, 1200), (2, b, 8000, 200), (3, a, 9500, 1700)]
        {
            let mut o = seen(at, 1, q, Some(&[3, 2, 0, 0]));
            (o.turnaround_us, o.own_us) = (Some(turnaround), Some(own));
            m.apply(&o);
        }
        let u = &m.units[&1];
        assert_eq!(u.turnarounds_us, [8000, 9000, 9500]);
        assert_eq!(u.quantile_us(0.5), Some(9000));
        assert_eq!(u.own_us, [1200, 200, 1700]);
        assert_eq!(u.own_by_request[a], [1200, 1700]);
        assert_eq!(u.own_by_request[b], [200]);
    }
}
