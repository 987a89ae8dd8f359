//! The access rule matcher (src/access/rules.rs) on hostile rules and requests: the
//! first bytes make a policy, the rest is the request PDU. Checked against a plain
//! model: a read always passes, `read_only` refuses everything else, and otherwise a
//! write passes exactly when some rule covers its unit, function and every address it
//! writes, one by one.
#![no_main]

use libfuzzer_sys::fuzz_target;
use mbgate::access::{Policy, UnitSet, WriteRule, Why};
use mbgate::frame::function::{only_reads, written};

fn rule(b: &[u8]) -> WriteRule {
    let word = |i: usize| u16::from_be_bytes([b[i], b[i + 1]]);
    WriteRule {
        units: (b[0] & 1 != 0).then(|| [b[1], b[2]].into_iter().collect::<UnitSet>()),
        functions: (b[0] & 2 != 0).then(|| vec![b[3] & 0x7F, b[4] & 0x7F]),
        addresses: (b[0] & 4 != 0).then(|| (word(5).min(word(7)), word(5).max(word(7)))),
    }
}

fn covers(r: &WriteRule, unit: u8, pdu: &[u8]) -> bool {
    let fc = pdu[0];
    let unit_ok = r.units.is_none_or(|u| u.contains(unit));
    let fc_ok = r.functions.as_ref().is_none_or(|f| f.contains(&fc));
    let addr_ok = match (r.addresses, written(pdu)) {
        (None, _) => true,
        (Some(_), None) => false,
        (Some((lo, hi)), Some((a, n))) => (0..u32::from(n.max(1)))
            .all(|i| (u32::from(lo)..=u32::from(hi)).contains(&(u32::from(a) + i))),
    };
    unit_ok && fc_ok && addr_ok
}

fuzz_target!(|data: &[u8]| {
    // flags, unit, then up to three rules of 9 bytes, then the PDU.
    let [flags, unit, rest @ ..] = data else { return };
    let n = usize::from(flags >> 1) % 4;
    if rest.len() < 9 * n + 1 {
        return;
    }
    let (rules, pdu) = rest.split_at(9 * n);
    let policy = Policy {
        read_only: flags & 1 != 0,
        write: rules.chunks(9).map(rule).collect(),
    };
    let got = policy.permits(*unit, pdu);
    if only_reads(pdu) {
        assert_eq!(got, Ok(()));
    } else if policy.read_only {
        assert_eq!(got, Err(Why::ReadOnly));
    } else {
        let model = policy.write.is_empty() || policy.write.iter().any(|r| covers(r, *unit, pdu));
        assert_eq!(got.is_ok(), model);
    }
});
