//! Answering a request from the model (pure; the moment in the capture's time is
//! passed in): as the device answered it, or as it would have from what it was seen
//! to hold (docs/simulator.md "Replaying a device", the rules in order).

use super::model::{is_write, Model, ReplayOutcome, Unit};
use crate::tools::sim::generic::{pack, registers};

/// What the user chose for what the capture does not say.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Choices {
    /// The exception for an address never read (02, illegal data address, unless
    /// `--unknown-exception` says otherwise).
    pub(crate) unknown: u8,
    /// `--read-only`: refuse every write.
    pub(crate) read_only: bool,
    /// `--timeline`: values as they were at the same time into the capture.
    pub(crate) timeline: bool,
}

impl Default for Choices {
    fn default() -> Self {
        Self {
            unknown: 2,
            read_only: false,
            timeline: false,
        }
    }
}

/// Modbus exception 01: the device does not serve this function.
const ILLEGAL_FUNCTION: u8 = 1;
/// Modbus exception 03: a malformed request.
const ILLEGAL_DATA_VALUE: u8 = 3;

fn word(pdu: &[u8], at: usize) -> u16 {
    u16::from_be_bytes([pdu[at], pdu[at + 1]])
}

impl Model {
    /// Long because it is the replay's rules in their order (numbered below), each an
    /// early return on the same unit's model: apart, the order would be hidden.
    ///
    /// The reply PDU `unit` gives to `pdu` (`None`: silence). `moment`: where in the
    /// capture's time a `--timeline` replay is (µs since the epoch), `None` for the
    /// latest values. A write changes the model unless refused.
    pub(crate) fn answer(
        &mut self,
        unit: u8,
        pdu: &[u8],
        moment: Option<u64>,
        choices: &Choices,
    ) -> Option<Vec<u8>> {
        // A unit never seen on the line is not there: silence, as on a bus.
        let u = self.units.get_mut(&unit)?;
        let &function = pdu.first()?;
        let exception = |code: u8| Some(vec![function | 0x80, code]);
        if is_write(function) && choices.read_only {
            return exception(u.write_exception.map_or(ILLEGAL_FUNCTION, |(_, c)| c));
        }
        // 1. This very request was seen: an exception or silence as then.
        match u.outcomes.get(pdu) {
            Some((_, ReplayOutcome::Exception(c))) => return exception(*c),
            Some((_, ReplayOutcome::Silent)) => return None,
            _ => {}
        }
        // Every request of this function went unanswered: it is not answered now.
        let answered = u.functions.get(&function).copied();
        let seen_function = answered.is_some();
        if answered == Some(0) {
            return None;
        }
        match function {
            // 2. A read: the values, if every address asked was seen.
            1..=4 => {
                // The quantities the Modbus application protocol allows a read.
                let most = if function <= 2 { 2000 } else { 125 };
                if pdu.len() != 5 || word(pdu, 3) == 0 || word(pdu, 3) > most {
                    return exception(ILLEGAL_DATA_VALUE);
                }
                let (addr, n) = (word(pdu, 1), word(pdu, 3));
                let table = &u.tables[usize::from(function - 1)];
                let values: Option<Vec<u16>> = (0..n)
                    .map(|i| {
                        let a = addr.checked_add(i)?;
                        table.get(&a)?.value(moment)
                    })
                    .collect();
                let Some(values) = values else {
                    return exception(choices.unknown);
                };
                let data = if function <= 2 {
                    pack(&values.iter().map(|&v| v != 0).collect::<Vec<_>>())
                } else {
                    registers(&values)
                };
                Some([vec![function, data.len() as u8], data].concat())
            }
            // 3. A write: into the model, answered as a device does.
            0x05 | 0x06 | 0x0F | 0x10 => {
                let Some((table, values)) = Unit::written_by(pdu) else {
                    return exception(ILLEGAL_DATA_VALUE);
                };
                for (a, v) in values {
                    u.tables[table].entry(a).or_default().written = Some(v);
                }
                Some(if function <= 6 {
                    pdu.to_vec()
                } else {
                    pdu[..5].to_vec()
                })
            }
            // 4. Anything else: its recorded reply, else an exception.
            _ => match u.outcomes.get(pdu) {
                Some((_, ReplayOutcome::Reply(r))) => Some(r.clone()),
                _ if seen_function => exception(choices.unknown),
                _ => exception(ILLEGAL_FUNCTION),
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Framing;
    use crate::tools::sim::replay::learn::{Observation, RecordedReply};

    fn model() -> Model {
        let mut m = Model::default();
        for (at, unit, q, r) in [
            (1000, 1, &[3, 0, 0, 0, 2][..], Some(&[3, 4, 0, 1, 0, 2][..])),
            (2000, 1, &[3, 0, 0, 0, 2], Some(&[3, 4, 0, 3, 0, 4])),
            (2500, 1, &[3, 0, 50, 0, 1], Some(&[0x83, 2])),
            (2600, 1, &[1, 0, 0, 0, 3], Some(&[1, 1, 0b101])),
            (2700, 1, &[6, 0, 60, 0, 1], Some(&[0x86, 4])),
            (
                2800,
                1,
                &[8, 0, 0, 0x12, 0x34],
                Some(&[8, 0, 0, 0x12, 0x34]),
            ),
            (3000, 2, &[4, 0, 0, 0, 1], None),
        ] {
            m.apply(&Observation {
                at_us: at,
                unit,
                request: q.to_vec(),
                seen: r.map_or(RecordedReply::Silent, |r| RecordedReply::Reply(r.to_vec())),
                turnaround_us: r.map(|_| 1000),
                wire_us: 0,
                line: 0,
                framing: Framing::Rtu,
            });
        }
        m.finish();
        m
    }

    #[test]
    fn answers_as_recorded_then_from_the_values_then_the_chosen_exception() {
        let mut m = model();
        let c = Choices::default();
        let mut ask = |unit, pdu: &[u8], moment| m.answer(unit, pdu, moment, &c);
        assert_eq!(ask(1, &[3, 0, 0, 0, 2], None), Some(vec![3, 4, 0, 3, 0, 4]));
        assert_eq!(
            ask(1, &[3, 0, 0, 0, 2], Some(1500)),
            Some(vec![3, 4, 0, 1, 0, 2])
        );
        assert_eq!(
            ask(1, &[3, 0, 1, 0, 1], None),
            Some(vec![3, 2, 0, 4]),
            "a part"
        );
        assert_eq!(ask(1, &[3, 0, 50, 0, 1], None), Some(vec![0x83, 2]));
        assert_eq!(
            ask(1, &[3, 0, 1, 0, 2], None),
            Some(vec![0x83, 2]),
            "never read"
        );
        assert_eq!(ask(1, &[1, 0, 0, 0, 3], None), Some(vec![1, 1, 0b101]));
        assert_eq!(
            ask(1, &[8, 0, 0, 0x12, 0x34], None),
            Some(vec![8, 0, 0, 0x12, 0x34])
        );
        assert_eq!(ask(1, &[8, 0, 1, 0, 0], None), Some(vec![0x88, 2]));
        assert_eq!(ask(1, &[0x2B, 0x0E, 1, 0], None), Some(vec![0xAB, 1]));
        assert_eq!(ask(2, &[4, 0, 0, 0, 1], None), None, "silent as then");
        assert_eq!(ask(2, &[4, 0, 5, 0, 1], None), None, "never answered FC 04");
        assert_eq!(ask(9, &[3, 0, 0, 0, 1], None), None, "never seen");
        // A write, then the read sees it; the refused write is refused again.
        assert_eq!(ask(1, &[6, 0, 1, 0, 9], None), Some(vec![6, 0, 1, 0, 9]));
        assert_eq!(
            ask(1, &[3, 0, 0, 0, 2], Some(1500)),
            Some(vec![3, 4, 0, 1, 0, 9])
        );
        assert_eq!(ask(1, &[6, 0, 60, 0, 1], None), Some(vec![0x86, 4]));
        assert_eq!(
            ask(1, &[0x10, 0, 7, 0, 2, 4, 0, 1, 0, 2], None),
            Some(vec![0x10, 0, 7, 0, 2])
        );
        assert_eq!(ask(1, &[3, 0, 7, 0, 2], None), Some(vec![3, 4, 0, 1, 0, 2]));
    }

    #[test]
    fn read_only_refuses_writes_with_the_device_s_exception_and_the_choice_is_used() {
        let mut m = model();
        let c = Choices {
            unknown: 0x0B,
            read_only: true,
            timeline: false,
        };
        assert_eq!(m.answer(1, &[6, 0, 1, 0, 9], None, &c), Some(vec![0x86, 4]));
        assert_eq!(
            m.answer(1, &[5, 0, 1, 0xFF, 0], None, &c),
            Some(vec![0x85, 4])
        );
        assert_eq!(
            m.answer(1, &[3, 0, 1, 0, 1], None, &c),
            Some(vec![3, 2, 0, 4])
        );
        assert_eq!(
            m.answer(1, &[3, 0, 9, 0, 1], None, &c),
            Some(vec![0x83, 0x0B])
        );
        m.units.get_mut(&1).unwrap().write_exception = None;
        assert_eq!(m.answer(1, &[6, 0, 1, 0, 9], None, &c), Some(vec![0x86, 1]));
    }
}
