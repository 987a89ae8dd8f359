//! The `generic` profile: virtual devices by unit id, each with coils, discrete inputs,
//! holding and input registers, serving FC 01, 02, 03, 04, 05, 06, 0F, 10 and 17
//! (docs/protocol.md §1) with the standard exceptions: 01 for a function it does not serve,
//! 03 for a quantity or value out of range, 02 for an address out of range, checked in
//! that order as the Modbus application protocol does.
//!
//! A new device follows the reference simulator (docs/protocol.md §4): at least 10 coils and
//! 10 registers, input registers 0..5 hold its creation date and time (UTC: year,
//! month, day, hour, minute, second), discrete inputs are random.

use super::{exception_pdu, Answer};
use crate::frame::function::{ExceptionCode, FunctionCode as Fc};
use crate::frame::pdu;
use std::collections::BTreeMap;
use std::fmt;

/// Seed 003's smallest device: 10 coils, 10 registers.
pub(crate) const MIN_SIZE: usize = 10;
/// Every address a PDU can name.
pub(crate) const MAX_SIZE: usize = 65536;

/// One virtual device's tables.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Bank {
    pub(crate) coils: Vec<bool>,
    /// Discrete inputs (FC 02), by address: random from the seed, then changed only by
    /// the console's `set` (masters cannot write them).
    pub discrete: Vec<bool>,
    pub(crate) holding: Vec<u16>,
    pub(crate) input: Vec<u16>,
}

impl Bank {
    /// A device as the reference simulator creates one (docs/protocol.md §4): `bits` coils and discrete inputs (random),
    /// `registers` holding registers (zero) and input registers (0..5 the creation date
    /// and time, the rest zero). `random` supplies the discrete inputs.
    pub(crate) fn new(
        bits: usize,
        registers: usize,
        created: [u16; 6],
        random: &mut fastrand::Rng,
    ) -> Self {
        let mut input = vec![0; registers];
        for (slot, v) in input.iter_mut().zip(created) {
            *slot = v;
        }
        Self {
            coils: vec![false; bits],
            discrete: (0..bits).map(|_| random.bool()).collect(),
            holding: vec![0; registers],
            input,
        }
    }
}

/// What `--fill header` puts in holding registers, over and over: 24 bytes that spell
/// two whole MBAP frames with transaction id 0 (an FC 03 reply of one register, an
/// FC 16 echo) and many plausible headers at other offsets. A reply carrying them
/// looks like frames inside frames to a decoder that lost its place.
pub(crate) const HEADER_FILL: [u16; 12] = [
    0x0000, 0x0000, 0x0005, 0x0103, 0x0200, 0x0000, 0x0000, 0x0000, 0x0006, 0x0110, 0x0000, 0x0001,
];

/// Holding register `a` under `--fill header`.
pub fn header_fill(a: usize) -> u16 {
    HEADER_FILL[a % HEADER_FILL.len()]
}

impl Bank {
    /// Holding register N holds `fill(N)`.
    pub(crate) fn fill_holding(&mut self, fill: fn(usize) -> u16) {
        for (a, v) in self.holding.iter_mut().enumerate() {
            *v = fill(a);
        }
    }
}

impl fmt::Display for Bank {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let bits = |v: &[bool]| -> String {
            v.iter()
                .take(32)
                .map(|&b| if b { '1' } else { '0' })
                .collect()
        };
        let regs = |v: &[u16]| -> String {
            let shown: Vec<String> = v.iter().take(10).map(u16::to_string).collect();
            shown.join(" ")
        };
        write!(
            f,
            "{} coils, {} registers\n  coils    {}\n  discrete {}\n  holding  {}\n  input    {}",
            self.coils.len(),
            self.holding.len(),
            bits(&self.coils),
            bits(&self.discrete),
            regs(&self.holding),
            regs(&self.input),
        )
    }
}

/// The devices on the line, by unit id.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Generic {
    /// Each unit id (1..=247) that answers, and its tables.
    pub units: BTreeMap<u8, Bank>,
}

fn word(pdu: &[u8], at: usize) -> usize {
    usize::from(u16::from_be_bytes([pdu[at], pdu[at + 1]]))
}

/// `start..start + quantity` if it lies inside a table of `len` entries.
fn span(start: usize, quantity: usize, len: usize) -> Option<std::ops::Range<usize>> {
    (start + quantity <= len).then_some(start..start + quantity)
}

pub(crate) fn pack(bits: &[bool]) -> Vec<u8> {
    let mut out = vec![0u8; bits.len().div_ceil(8)];
    for (i, &b) in bits.iter().enumerate() {
        if b {
            out[i / 8] |= 1 << (i % 8);
        }
    }
    out
}

pub(crate) fn registers(values: &[u16]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_be_bytes()).collect()
}

impl Generic {
    /// Answers one request PDU. A unit id with no device gets silence, as on a bus.
    pub(crate) fn answer(&mut self, unit: u8, pdu: &[u8]) -> Answer {
        let Some(bank) = self.units.get_mut(&unit) else {
            return Answer::silent();
        };
        let code = Fc::new(pdu[0]);
        Answer::reply(match serve(bank, pdu) {
            Ok(data) => data,
            Err(e) => exception_pdu(code.base(), e),
        })
    }
}

/// Long because it is the table of function codes the device serves, one arm each,
/// in the order of the Modbus application protocol.
///
/// The normal response PDU, or the exception code. Sizes, quantities and values are
/// checked against the function code table as the gateway checks them
/// ([`pdu::check_request`]: 03), before addresses (02).
fn serve(bank: &mut Bank, pdu: &[u8]) -> Result<Vec<u8>, ExceptionCode> {
    const ADDRESS: ExceptionCode = ExceptionCode::ILLEGAL_DATA_ADDRESS;
    let code = Fc::new(pdu[0]);
    let sized = || pdu::check_request(pdu);
    match code {
        Fc::READ_COILS | Fc::READ_DISCRETE_INPUTS => {
            sized()?;
            let table = if code == Fc::READ_COILS {
                &bank.coils
            } else {
                &bank.discrete
            };
            let r = span(word(pdu, 1), word(pdu, 3), table.len()).ok_or(ADDRESS)?;
            let bytes = pack(&table[r]);
            Ok([vec![code.get(), bytes.len() as u8], bytes].concat())
        }
        Fc::READ_HOLDING_REGISTERS | Fc::READ_INPUT_REGISTERS => {
            sized()?;
            let table = if code == Fc::READ_HOLDING_REGISTERS {
                &bank.holding
            } else {
                &bank.input
            };
            let r = span(word(pdu, 1), word(pdu, 3), table.len()).ok_or(ADDRESS)?;
            let bytes = registers(&table[r]);
            Ok([vec![code.get(), bytes.len() as u8], bytes].concat())
        }
        Fc::WRITE_SINGLE_COIL => {
            sized()?;
            let slot = bank.coils.get_mut(word(pdu, 1)).ok_or(ADDRESS)?;
            *slot = word(pdu, 3) == 0xFF00;
            Ok(pdu.to_vec())
        }
        Fc::WRITE_SINGLE_REGISTER => {
            sized()?;
            let slot = bank.holding.get_mut(word(pdu, 1)).ok_or(ADDRESS)?;
            *slot = word(pdu, 3) as u16;
            Ok(pdu.to_vec())
        }
        Fc::WRITE_MULTIPLE_COILS => {
            sized()?;
            let r = span(word(pdu, 1), word(pdu, 3), bank.coils.len()).ok_or(ADDRESS)?;
            for (i, slot) in bank.coils[r].iter_mut().enumerate() {
                *slot = pdu[6 + i / 8] & (1 << (i % 8)) != 0;
            }
            Ok(pdu[..5].to_vec())
        }
        Fc::WRITE_MULTIPLE_REGISTERS => {
            sized()?;
            let r = span(word(pdu, 1), word(pdu, 3), bank.holding.len()).ok_or(ADDRESS)?;
            for (i, slot) in bank.holding[r].iter_mut().enumerate() {
                *slot = word(pdu, 6 + 2 * i) as u16;
            }
            Ok(pdu[..5].to_vec())
        }
        Fc::READ_WRITE_MULTIPLE_REGISTERS => {
            sized()?;
            let len = bank.holding.len();
            let read = span(word(pdu, 1), word(pdu, 3), len).ok_or(ADDRESS)?;
            let write = span(word(pdu, 5), word(pdu, 7), len).ok_or(ADDRESS)?;
            // The write is performed before the read (Modbus application protocol).
            for (i, slot) in bank.holding[write].iter_mut().enumerate() {
                *slot = word(pdu, 10 + 2 * i) as u16;
            }
            let bytes = registers(&bank.holding[read]);
            Ok([vec![code.get(), bytes.len() as u8], bytes].concat())
        }
        _ => Err(ExceptionCode::ILLEGAL_FUNCTION),
    }
}

/// Year, month, day, hour, minute, second (UTC), for input registers 0..5
/// (docs/protocol.md §4).
pub(crate) fn civil_time(t: std::time::SystemTime) -> [u16; 6] {
    // `YYYY-MM-DDTHH:MM:SSZ`
    let s = humantime::format_rfc3339_seconds(t).to_string();
    let field = |at: usize, len: usize| {
        s.get(at..at + len)
            .and_then(|f| f.parse().ok())
            .unwrap_or(0)
    };
    [
        field(0, 4),
        field(5, 2),
        field(8, 2),
        field(11, 2),
        field(14, 2),
        field(17, 2),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::hex::parse as bytes;

    fn device() -> Generic {
        let mut rng = fastrand::Rng::with_seed(1);
        let mut bank = Bank::new(40, 20, [2026, 11, 21, 5, 30, 0], &mut rng);
        bank.holding[0] = 0xFF;
        let mut g = Generic::default();
        g.units.insert(1, bank);
        g
    }

    fn reply(g: &mut Generic, pdu: &str) -> Vec<u8> {
        g.answer(1, &bytes(pdu)).reply.expect("a reply")
    }

    #[test]
    fn every_function_code() {
        let mut g = device();
        assert_eq!(reply(&mut g, "03 00 00 00 02"), bytes("03 04 00 FF 00 00"));
        assert_eq!(
            reply(&mut g, "04 00 00 00 06"),
            bytes("04 0C 07 EA 00 0B 00 15 00 05 00 1E 00 00")
        );
        assert_eq!(reply(&mut g, "06 00 03 12 34"), bytes("06 00 03 12 34"));
        assert_eq!(
            reply(&mut g, "10 00 04 00 02 04 00 0A 00 0B"),
            bytes("10 00 04 00 02")
        );
        assert_eq!(
            reply(&mut g, "03 00 03 00 03"),
            bytes("03 06 12 34 00 0A 00 0B")
        );
        assert_eq!(reply(&mut g, "05 00 01 FF 00"), bytes("05 00 01 FF 00"));
        // Seed 004: coils 20..38 = CD 6B 05, written with FC 0F and read back.
        assert_eq!(
            reply(&mut g, "0F 00 14 00 13 03 CD 6B 05"),
            bytes("0F 00 14 00 13")
        );
        assert_eq!(reply(&mut g, "01 00 14 00 13"), bytes("01 03 CD 6B 05"));
        assert_eq!(reply(&mut g, "01 00 00 00 03"), bytes("01 01 02"));
        // FC 17: write 2 registers at 8, read 3 from 7, write first.
        assert_eq!(
            reply(&mut g, "17 00 07 00 03 00 08 00 02 04 AA AA BB BB"),
            bytes("17 06 00 00 AA AA BB BB")
        );
        let discrete = g.units[&1].discrete.clone();
        let got = reply(&mut g, "02 00 00 00 08");
        assert_eq!(got[..2], [2, 1]);
        assert_eq!(got[2], pack(&discrete[..8])[0]);
    }

    #[test]
    fn exceptions_in_order_function_value_address() {
        let mut g = device();
        assert_eq!(reply(&mut g, "07"), bytes("87 01"));
        assert_eq!(reply(&mut g, "41 00"), bytes("C1 01"));
        assert_eq!(reply(&mut g, "03 00 00 00 00"), bytes("83 03"));
        assert_eq!(reply(&mut g, "03 00 00 00 7E"), bytes("83 03"));
        assert_eq!(reply(&mut g, "03 00 13 00 02"), bytes("83 02"));
        assert_eq!(
            reply(&mut g, "03 FF FF 00 7E"),
            bytes("83 03"),
            "value before address"
        );
        assert_eq!(reply(&mut g, "05 00 01 12 34"), bytes("85 03"));
        assert_eq!(reply(&mut g, "05 00 28 FF 00"), bytes("85 02"));
        assert_eq!(reply(&mut g, "06 00 14 00 01"), bytes("86 02"));
        assert_eq!(reply(&mut g, "0F 00 00 00 09 01 FF"), bytes("8F 03"));
        assert_eq!(reply(&mut g, "0F 00 26 00 03 01 07"), bytes("8F 02"));
        assert_eq!(
            reply(&mut g, "10 00 13 00 02 04 00 01 00 02"),
            bytes("90 02")
        );
        assert_eq!(reply(&mut g, "10 00 00 00 02 02 00 01"), bytes("90 03"));
        assert_eq!(
            reply(&mut g, "17 00 00 00 01 00 13 00 02 04 00 01 00 02"),
            bytes("97 02")
        );
        assert_eq!(reply(&mut g, "01 00 00 07 D1"), bytes("81 03"));
        assert_eq!(reply(&mut g, "02 00 27 00 02"), bytes("82 02"));
        assert_eq!(reply(&mut g, "04 00 14 00 01"), bytes("84 02"));
        assert_eq!(g.answer(9, &bytes("03 00 00 00 01")), Answer::silent());
    }

    #[test]
    fn creation_time_is_civil_utc() {
        let at = |secs| civil_time(std::time::UNIX_EPOCH + std::time::Duration::from_secs(secs));
        assert_eq!(at(0), [1970, 1, 1, 0, 0, 0]);
        // 2026-11-21T05:30:00Z
        assert_eq!(at(1_795_239_000), [2026, 11, 21, 5, 30, 0]);
        assert_eq!(at(951_782_400), [2000, 2, 29, 0, 0, 0]);
    }
}
