//! The replayed devices' model (pure): for each unit, every register and bit it was
//! seen to hold and when, the latest outcome of each distinct request (a reply, an
//! exception, silence), the exception it gave to writes, and its reply times
//! (docs/simulator.md "Replaying a device"). Built by applying observations as the
//! files are read, in any order: each thing kept says when it was seen, so where
//! captures disagree the latest wins; [`Model::finish`] then makes the reply times.
//!
//! Compact, so a capture of any length replays in little memory: a value is kept
//! again only when it changed (and only the latest unless `--timeline`), a reply's
//! times as 32-bit microseconds.

use super::learn::{Observation, Recorded, RecordedReply, Wires};
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
    /// (when, value) each time it changed, in time order: a value seen again
    /// unchanged only moves `last_at`.
    pub(crate) history: Vec<(u64, u16)>,
    /// When the last value of `history` was last seen.
    last_at: u64,
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

    /// `value` seen at `at`; with `latest_only`, only the latest value is kept.
    fn record(&mut self, at: u64, value: u16, latest_only: bool) {
        let Some(&(_, last)) = self.history.last() else {
            self.history.push((at, value));
            self.last_at = at;
            return;
        };
        if at >= self.last_at {
            // In time order, as nearly every observation comes.
            if value != last {
                if latest_only {
                    self.history.clear();
                }
                self.history.push((at, value));
            }
            self.last_at = at;
            return;
        }
        if latest_only {
            return;
        }
        // Older than the latest seen (another file, a pipelined reply): in its place.
        let n = self.history.partition_point(|&(t, _)| t <= at);
        let after_last_change = n == self.history.len();
        self.history.insert(n, (at, value));
        if after_last_change && value != last {
            // The last value was seen again after it (at `last_at`): it holds from
            // then on.
            self.history.push((self.last_at, last));
        }
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
    /// By function code seen: how many of its distinct requests got an answer (a
    /// reply or an exception) the latest time, so an answer need not look through
    /// every request of the unit.
    pub(crate) functions: BTreeMap<u8, usize>,
    /// The latest exception it gave to a write (FC 05, 06, 0F, 10, 16, 17), and when.
    pub(crate) write_exception: Option<(u64, u8)>,
    /// Request out to reply in, µs, sorted (as recorded, for the summary); made by
    /// [`Model::finish`].
    pub(crate) turnarounds_us: Vec<u32>,
    /// The device's own times of those (less the wire's: `learn::Wires`), µs, in the
    /// order recorded: the replay's delays are drawn from them. Made by
    /// [`Model::finish`].
    pub(crate) own_us: Vec<u32>,
    /// The same, request by request (a device takes longer for some). While the
    /// files are read: indices into `replies`.
    pub(crate) own_by_request: HashMap<Vec<u8>, Vec<u32>>,
    /// Each reply's times as recorded, until [`Model::finish`] knows which lines had
    /// a wire and makes the device's own of them.
    replies: Vec<ReplyTimes>,
    /// How its line carried it.
    pub(crate) framing: Option<Framing>,
}

/// One reply's times as recorded, 32-bit microseconds (71 minutes: far past any
/// reply a gateway waits for; longer is kept as that).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct ReplyTimes {
    turnaround_us: u32,
    wire_us: u32,
    line: u32,
}

fn us32(us: u64) -> u32 {
    u32::try_from(us).unwrap_or(u32::MAX)
}

/// Every replayed unit, and the capture's first moment (the timeline's start).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(crate) struct Model {
    pub(crate) units: BTreeMap<u8, Unit>,
    pub(crate) start_us: Option<u64>,
    pub(crate) end_us: Option<u64>,
    /// Keep each value's latest only: a replay that is not `--timeline` never asks
    /// for another.
    pub(crate) latest_only: bool,
    /// Which lines had a wire, from the replies seen so far.
    wires: Wires,
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

    /// The values a write `request` at `at` set, recorded.
    fn learn_write(&mut self, at: u64, request: &[u8], latest_only: bool) {
        if let Some((table, values)) = Unit::written_by(request) {
            for (a, v) in values {
                self.tables[table]
                    .entry(a)
                    .or_default()
                    .record(at, v, latest_only);
            }
        }
    }

    /// A reply's time, `t` after its request `o`, kept with the others of that request.
    fn reply_time(&mut self, o: &Observation, t: u64) {
        let index = us32(self.replies.len() as u64);
        self.replies.push(ReplyTimes {
            turnaround_us: us32(t),
            wire_us: us32(o.wire_us),
            line: us32(o.line as u64),
        });
        match self.own_by_request.get_mut(&o.request) {
            Some(v) => v.push(index),
            None => {
                self.own_by_request.insert(o.request.clone(), vec![index]);
            }
        }
    }

    /// What a normal reply to a read says about the table it read.
    fn learn_read(&mut self, at: u64, request: &[u8], reply: &[u8], latest_only: bool) {
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
            self.tables[table]
                .entry(a)
                .or_default()
                .record(at, v, latest_only);
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
        self.turnarounds_us.get(i).map(|&t| u64::from(t))
    }
}

impl Model {
    /// A model for a replay: with `timeline`, every value over time; else the latest.
    pub(crate) fn new(timeline: bool) -> Model {
        Model {
            latest_only: !timeline,
            ..Model::default()
        }
    }

    /// Applies what one request showed, in any order: what is kept says when it was
    /// seen, so the latest wins.
    pub(crate) fn apply(&mut self, o: &Observation) {
        let Some(&function) = o.request.first() else {
            return;
        };
        self.start_us = Some(self.start_us.map_or(o.at_us, |s| s.min(o.at_us)));
        self.end_us = Some(self.end_us.map_or(o.at_us, |e| e.max(o.at_us)));
        let latest_only = self.latest_only;
        let unit = self.units.entry(o.unit).or_default();
        unit.framing.get_or_insert(o.framing);
        let outcome = match &o.seen {
            RecordedReply::Silent => ReplayOutcome::Silent,
            RecordedReply::Reply(pdu) if pdu.first().is_some_and(|f| f & 0x80 != 0) => {
                let code = pdu.get(1).copied().unwrap_or(0);
                if is_write(function) && unit.write_exception.is_none_or(|(t, _)| t <= o.at_us) {
                    unit.write_exception = Some((o.at_us, code));
                }
                ReplayOutcome::Exception(code)
            }
            RecordedReply::Reply(pdu) => {
                match function {
                    1..=4 => unit.learn_read(o.at_us, &o.request, pdu, latest_only),
                    _ => unit.learn_write(o.at_us, &o.request, latest_only),
                }
                ReplayOutcome::Reply(pdu.clone())
            }
        };
        if let Some(t) = o.turnaround_us {
            let recorded = Recorded {
                line: o.line,
                turnaround_us: t,
                wire_us: o.wire_us,
            };
            self.wires.saw(recorded);
            unit.reply_time(o, t);
        }
        let answered = unit.functions.entry(function).or_insert(0);
        let silent = outcome == ReplayOutcome::Silent;
        match unit.outcomes.get_mut(&o.request) {
            Some((at, _)) if *at > o.at_us => {}
            Some(kept) => {
                match (kept.1 == ReplayOutcome::Silent, silent) {
                    (true, false) => *answered += 1,
                    (false, true) => *answered -= 1,
                    _ => {}
                }
                *kept = (o.at_us, outcome);
            }
            None => {
                *answered += usize::from(!silent);
                unit.outcomes.insert(o.request.clone(), (o.at_us, outcome));
            }
        }
    }

    /// Every file read: each reply's own time, now that it is known which lines had
    /// a wire, and the reply times sorted for the summary.
    pub(crate) fn finish(&mut self) {
        for unit in self.units.values_mut() {
            let replies = std::mem::take(&mut unit.replies);
            unit.own_us = replies
                .iter()
                .map(|r| {
                    us32(self.wires.own(Recorded {
                        line: r.line as usize,
                        turnaround_us: u64::from(r.turnaround_us),
                        wire_us: u64::from(r.wire_us),
                    }))
                })
                .collect();
            for times in unit.own_by_request.values_mut() {
                for t in times.iter_mut() {
                    *t = unit.own_us[*t as usize];
                }
            }
            unit.turnarounds_us = replies.iter().map(|r| r.turnaround_us).collect();
            unit.turnarounds_us.sort_unstable();
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
            wire_us: 0,
            line: 0,
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
        m.finish();
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
            (o.turnaround_us, o.wire_us) = (Some(turnaround), turnaround - own);
            m.apply(&o);
        }
        m.finish();
        let u = &m.units[&1];
        assert_eq!(u.turnarounds_us, [8000, 9000, 9500]);
        assert_eq!(u.quantile_us(0.5), Some(9000));
        assert_eq!(u.own_us, [1200, 200, 1700]);
        assert_eq!(u.own_by_request[a], [1200, 1700]);
        assert_eq!(u.own_by_request[b], [200]);
    }

    /// A value kept again only when it changed, and the latest only unless the replay
    /// is `--timeline`: a million reads of one register that changes ten times keep
    /// ten values, or one; the value at any moment is the same as with every read
    /// kept, whatever order the reads came in.
    #[test]
    fn values_are_kept_at_their_changes_only() {
        let reads: Vec<(u64, u16)> = (0..1_000_000u64)
            .map(|i| (i, (i / 100_000) as u16))
            .collect();
        for latest_only in [false, true] {
            let mut cell = Cell::default();
            for &(at, v) in &reads {
                cell.record(at, v, latest_only);
            }
            assert_eq!(cell.history.len(), if latest_only { 1 } else { 10 });
            assert_eq!(cell.value(None), Some(9));
            if !latest_only {
                for t in [0, 99_999, 100_000, 512_345, 999_999, 5_000_000] {
                    assert_eq!(cell.value(Some(t)), Some((t.min(999_999) / 100_000) as u16));
                }
            }
        }
        // Out of order (a second file, a pipelined reply): the latest still wins,
        // and a value older than the last seen one takes its place in time.
        let mut cell = Cell::default();
        for (at, v) in [(10, 1), (20, 1), (30, 1), (25, 2), (5, 3), (40, 1)] {
            cell.record(at, v, false);
        }
        let at = |t| cell.value(Some(t));
        assert_eq!(
            (at(5), at(10), at(25), at(30), at(40)),
            (Some(3), Some(1), Some(2), Some(1), Some(1))
        );
        let mut latest = Cell::default();
        for (at, v) in [(10, 1), (30, 4), (20, 2)] {
            latest.record(at, v, true);
        }
        assert_eq!(latest.history, [(30, 4)]);
    }

    /// Applied in any order, the model is the same: a write's exception and a
    /// request's outcome are the latest by time, not the last applied.
    #[test]
    fn the_order_observations_come_in_changes_nothing() {
        let all = [
            seen(1000, 1, &[6, 0, 1, 0, 1], Some(&[0x86, 2])),
            seen(3000, 1, &[6, 0, 1, 0, 1], Some(&[0x86, 4])),
            seen(2000, 1, &[3, 0, 1, 0, 1], Some(&[3, 2, 0, 7])),
            seen(4000, 1, &[3, 0, 1, 0, 1], None),
        ];
        let mut forward = Model::new(true);
        let mut backward = Model::new(true);
        for o in &all {
            forward.apply(o);
        }
        for o in all.iter().rev() {
            backward.apply(o);
        }
        forward.finish();
        backward.finish();
        let (f, b) = (&forward.units[&1], &backward.units[&1]);
        assert_eq!(f.write_exception, Some((3000, 4)));
        assert_eq!(b.write_exception, Some((3000, 4)));
        assert_eq!(f.outcomes, b.outcomes);
        // FC 06 answered (with exceptions); FC 03 silent the latest time it was asked.
        assert_eq!(f.functions, BTreeMap::from([(3, 0), (6, 1)]));
        assert_eq!(b.functions, f.functions);
        assert_eq!(f.tables, b.tables);
        assert_eq!(f.turnarounds_us, b.turnarounds_us);
    }
}
