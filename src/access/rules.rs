//! What a master may do (docs/design.md §4.3, docs/security.md "What a master may
//! do"): a listener's and a role's policy, and the one decision for a request. Plain
//! data and pure: fuzzed and property-tested with hostile requests and rules.
//!
//! A request that only reads ([`function::only_reads`]) is never refused here. Any
//! other (a write, diagnostics, a code mbgate does not know) must be permitted by every
//! policy that applies: the listener's, and on a TLS listener the master's role's. A
//! policy permits a write unless it is `read_only`; with `write` rules, only a write
//! that some rule matches. Rules only permit: their order does not matter, and the
//! stricter policy wins.

use crate::frame::function;
use std::fmt;

/// A set of unit ids, 0 to 255.
#[derive(Clone, Copy, PartialEq, Eq, Default)]
pub struct UnitSet([u64; 4]);

impl UnitSet {
    /// Adds `unit`.
    pub(crate) fn insert(&mut self, unit: u8) {
        self.0[usize::from(unit / 64)] |= 1 << (unit % 64);
    }

    /// Is `unit` in the set?
    pub fn contains(&self, unit: u8) -> bool {
        self.0[usize::from(unit / 64)] & (1 << (unit % 64)) != 0
    }

    fn ids(&self) -> impl Iterator<Item = u8> + '_ {
        (0..=255u8).filter(|u| self.contains(*u))
    }
}

impl FromIterator<u8> for UnitSet {
    fn from_iter<I: IntoIterator<Item = u8>>(iter: I) -> Self {
        let mut set = UnitSet::default();
        for u in iter {
            set.insert(u);
        }
        set
    }
}

impl fmt::Debug for UnitSet {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_set().entries(self.ids()).finish()
    }
}

impl fmt::Display for UnitSet {
    /// As the file writes it: `[1, "10-20"]`, runs of three or more as ranges.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let ids: Vec<u8> = self.ids().collect();
        f.write_str(&id_list(&ids))
    }
}

/// Unit ids (sorted, distinct) as the configuration file writes a list of them:
/// `[1, "10-20"]`, runs of three or more as `"A-B"` strings.
pub(crate) fn id_list(ids: &[u8]) -> String {
    let mut parts = Vec::new();
    let mut i = 0;
    while i < ids.len() {
        let mut j = i;
        while j + 1 < ids.len() && ids[j + 1] == ids[j] + 1 {
            j += 1;
        }
        if j >= i + 2 {
            parts.push(format!("\"{}-{}\"", ids[i], ids[j]));
        } else {
            parts.extend(ids[i..=j].iter().map(u8::to_string));
        }
        i = j + 1;
    }
    format!("[{}]", parts.join(", "))
}

/// One `write` rule: the writes it permits. Each part left out matches anything.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct WriteRule {
    /// The master's unit ids (before any `remap`).
    pub units: Option<UnitSet>,
    /// Function codes.
    pub functions: Option<Vec<u8>>,
    /// First and last address, inclusive: every address the write writes must be in it
    /// ([`function::written`]). A rule with addresses matches no write that has no
    /// address range (FC 08, 21, 0x2B, codes mbgate does not know).
    pub addresses: Option<(u16, u16)>,
}

impl WriteRule {
    /// Does it permit this write to `unit`?
    pub(crate) fn matches(&self, unit: u8, pdu: &[u8]) -> bool {
        let Some(&fc) = pdu.first() else {
            return false;
        };
        if self.units.is_some_and(|u| !u.contains(unit)) {
            return false;
        }
        if self.functions.as_ref().is_some_and(|f| !f.contains(&fc)) {
            return false;
        }
        match self.addresses {
            None => true,
            Some((lo, hi)) => function::written(pdu).is_some_and(|(addr, count)| {
                let last = u32::from(addr) + u32::from(count.max(1)) - 1;
                addr >= lo && last <= u32::from(hi)
            }),
        }
    }
}

impl fmt::Display for WriteRule {
    /// As the file writes it: `{ units = [1], functions = [6, 16], addresses = "0-99" }`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut parts = Vec::new();
        if let Some(u) = &self.units {
            parts.push(format!("units = {u}"));
        }
        if let Some(fcs) = &self.functions {
            let fcs: Vec<String> = fcs.iter().map(u8::to_string).collect();
            parts.push(format!("functions = [{}]", fcs.join(", ")));
        }
        if let Some((lo, hi)) = self.addresses {
            parts.push(format!("addresses = \"{lo}-{hi}\""));
        }
        write!(f, "{{ {} }}", parts.join(", "))
    }
}

/// What a listener or a role lets a master do beyond reading.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Policy {
    /// No request that may act on the device: every one is answered 0x01.
    pub read_only: bool,
    /// The writes permitted; empty (and not `read_only`): every write.
    pub write: Vec<WriteRule>,
}

/// Why a policy refused a request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Why {
    /// `read_only = true`.
    ReadOnly,
    /// It has `write` rules and none matches.
    NoRule,
}

impl Policy {
    /// May a master under this policy send `pdu` to `unit`? A read always may.
    pub fn permits(&self, unit: u8, pdu: &[u8]) -> Result<(), Why> {
        if function::only_reads(pdu) {
            return Ok(());
        }
        if self.read_only {
            return Err(Why::ReadOnly);
        }
        if self.write.is_empty() || self.write.iter().any(|r| r.matches(unit, pdu)) {
            return Ok(());
        }
        Err(Why::NoRule)
    }

    /// No restriction at all: reads and every write.
    pub(crate) fn is_open(&self) -> bool {
        !self.read_only && self.write.is_empty()
    }

    /// What it lets a master do, in a few words (`mbgate check-config`, the start-up
    /// log).
    pub(crate) fn describe(&self) -> String {
        if self.read_only {
            "read only".into()
        } else if self.write.is_empty() {
            "read and write".into()
        } else {
            let rules: Vec<String> = self.write.iter().map(WriteRule::to_string).collect();
            format!("read, and write only as {}", rules.join(" or "))
        }
    }
}

/// A request refused: by whose policy, and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Denied<'a> {
    /// `None`: the listener's policy; else the role's name.
    pub(crate) role: Option<&'a str>,
    /// What it refused.
    pub(crate) why: Why,
}

impl fmt::Display for Denied<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let whose = match self.role {
            None => "the listener".to_owned(),
            Some(r) => format!("role {r:?}"),
        };
        match self.why {
            Why::ReadOnly => write!(f, "{whose} is read only"),
            Why::NoRule => write!(f, "no write rule of {whose} permits it"),
        }
    }
}

/// The decision for one request to `unit`: the listener's policy, then the role's (a
/// TLS master's), each must permit it.
pub(crate) fn decide<'a>(
    listener: &Policy,
    role: Option<(&'a str, &Policy)>,
    unit: u8,
    pdu: &[u8],
) -> Result<(), Denied<'a>> {
    listener
        .permits(unit, pdu)
        .map_err(|why| Denied { role: None, why })?;
    if let Some((name, policy)) = role {
        policy.permits(unit, pdu).map_err(|why| Denied {
            role: Some(name),
            why,
        })?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn id_lists_write_runs_of_three_or_more_as_ranges() {
        assert_eq!(id_list(&[]), "[]");
        assert_eq!(
            id_list(&[1, 2, 5, 10, 11, 12, 20]),
            r#"[1, 2, 5, "10-12", 20]"#
        );
        assert_eq!(id_list(&[0, 1, 2, 3, 255]), r#"["0-3", 255]"#);
    }

    const WRITES: [&[u8]; 6] = [
        &[0x05, 0, 10, 0xFF, 0],
        &[0x06, 0, 10, 0, 7],
        &[0x0F, 0, 10, 0, 3, 1, 5],
        &[0x10, 0, 10, 0, 2, 4, 0, 1, 0, 2],
        &[0x16, 0, 10, 0, 0xF2, 0, 0x25],
        &[0x17, 0, 0, 0, 1, 0, 10, 0, 1, 2, 0, 9],
    ];

    fn rule(units: Option<&[u8]>, fcs: Option<&[u8]>, addrs: Option<(u16, u16)>) -> WriteRule {
        WriteRule {
            units: units.map(|u| u.iter().copied().collect()),
            functions: fcs.map(<[u8]>::to_vec),
            addresses: addrs,
        }
    }

    #[test]
    fn read_only_refuses_every_write_and_no_read() {
        let ro = Policy {
            read_only: true,
            write: vec![],
        };
        for w in WRITES {
            assert_eq!(ro.permits(1, w), Err(Why::ReadOnly), "{w:02X?}");
        }
        for other in [
            &[0x08, 0, 1, 0, 0][..],
            &[0x15, 0],
            &[0x41, 1],
            &[0x2B, 0x0D],
        ] {
            assert_eq!(ro.permits(1, other), Err(Why::ReadOnly), "{other:02X?}");
        }
        for read in [
            &[3, 0, 0, 0, 1][..],
            &[1, 0, 0, 0, 8],
            &[0x2B, 0x0E, 1, 0],
            &[0x11],
        ] {
            assert_eq!(ro.permits(1, read), Ok(()), "{read:02X?}");
        }
        assert_eq!(Policy::default().permits(1, WRITES[0]), Ok(()));
    }

    #[test]
    fn a_rule_permits_only_within_its_units_functions_and_addresses() {
        let p = Policy {
            read_only: false,
            write: vec![rule(Some(&[1]), Some(&[6, 16]), Some((10, 11)))],
        };
        assert_eq!(p.permits(1, WRITES[1]), Ok(()), "FC 06 at 10");
        assert_eq!(p.permits(1, WRITES[3]), Ok(()), "FC 16 at 10..=11");
        assert_eq!(p.permits(2, WRITES[1]), Err(Why::NoRule), "another unit");
        assert_eq!(
            p.permits(1, WRITES[0]),
            Err(Why::NoRule),
            "FC 05 not listed"
        );
        assert_eq!(
            p.permits(1, &[0x10, 0, 10, 0, 3, 6, 0, 1, 0, 2, 0, 3]),
            Err(Why::NoRule),
            "10..=12 leaves the range"
        );
        // Without addresses: any address, and writes with no address range too.
        let any = rule(Some(&[1]), None, None);
        assert!(any.matches(1, &[0x08, 0, 1, 0, 0]) && any.matches(1, &[0x41]));
        let ranged = rule(None, None, Some((0, 0xFFFF)));
        assert!(!ranged.matches(1, &[0x08, 0, 1, 0, 0]), "no range to check");
        assert!(ranged.matches(1, &[0x10, 0xFF, 0xFF, 0, 1, 2, 0, 0]));
        assert!(
            !ranged.matches(1, &[0x10, 0xFF, 0xFF, 0, 2, 4, 0, 0, 0, 0]),
            "past the last address"
        );
        // FC 23: its written range counts, not its read range.
        let w23 = rule(None, Some(&[0x17]), Some((10, 10)));
        assert!(w23.matches(3, WRITES[5]));
    }

    #[test]
    fn both_policies_must_permit_and_the_refusal_names_whose() {
        let open = Policy::default();
        let ro = Policy {
            read_only: true,
            write: vec![],
        };
        assert_eq!(decide(&open, Some(("op", &open)), 1, WRITES[1]), Ok(()));
        let d = decide(&open, Some(("viewer", &ro)), 1, WRITES[1]).unwrap_err();
        assert_eq!(d.to_string(), "role \"viewer\" is read only");
        let d = decide(&ro, Some(("op", &open)), 1, WRITES[1]).unwrap_err();
        assert_eq!(d.to_string(), "the listener is read only");
        assert_eq!(decide(&ro, None, 1, &[3, 0, 0, 0, 1]), Ok(()));
    }

    #[test]
    fn printed_as_the_file_writes_them() {
        let r = rule(Some(&[1, 2, 3, 7]), Some(&[6, 16]), Some((100, 199)));
        assert_eq!(
            r.to_string(),
            "{ units = [\"1-3\", 7], functions = [6, 16], addresses = \"100-199\" }"
        );
        assert_eq!(Policy::default().describe(), "read and write");
    }

    /// The matcher against a plain model: every address the request writes, one by
    /// one, inside the rule's range; for any bytes at all (hostile requests).
    fn model(rule: &WriteRule, unit: u8, pdu: &[u8]) -> bool {
        let Some(&fc) = pdu.first() else { return false };
        let unit_ok = rule.units.is_none_or(|u| u.contains(unit));
        let fc_ok = rule.functions.as_ref().is_none_or(|f| f.contains(&fc));
        let addr_ok = match rule.addresses {
            None => true,
            Some((lo, hi)) => match function::written(pdu) {
                None => false,
                Some((a, n)) => (0..u32::from(n.max(1)))
                    .all(|i| (u32::from(lo)..=u32::from(hi)).contains(&(u32::from(a) + i))),
            },
        };
        unit_ok && fc_ok && addr_ok
    }

    fn any_rule() -> impl Strategy<Value = WriteRule> {
        (
            proptest::option::of(proptest::collection::vec(any::<u8>(), 0..4)),
            proptest::option::of(proptest::collection::vec(
                prop_oneof![
                    Just(5u8),
                    Just(6),
                    Just(15),
                    Just(16),
                    Just(22),
                    Just(23),
                    any::<u8>()
                ],
                0..4,
            )),
            proptest::option::of((any::<u16>(), any::<u16>())),
        )
            .prop_map(|(units, functions, addrs)| WriteRule {
                units: units.map(|u| u.into_iter().collect()),
                functions,
                addresses: addrs.map(|(a, b)| (a.min(b), a.max(b))),
            })
    }

    fn any_pdu() -> impl Strategy<Value = Vec<u8>> {
        prop_oneof![
            proptest::collection::vec(any::<u8>(), 0..12),
            (
                prop_oneof![Just(5u8), Just(6), Just(15), Just(16), Just(22), Just(23)],
                proptest::collection::vec(any::<u8>(), 0..12)
            )
                .prop_map(|(fc, mut rest)| {
                    rest.insert(0, fc);
                    rest
                }),
        ]
    }

    proptest! {
        // No failure file in the tree: a case found is kept by hand as a test.
        #![proptest_config(proptest::test_runner::Config { failure_persistence: None, ..Default::default() })]
        #[test]
        fn the_matcher_agrees_with_the_model(r in any_rule(), unit in any::<u8>(), pdu in any_pdu()) {
            prop_assert_eq!(r.matches(unit, &pdu), model(&r, unit, &pdu));
        }

        #[test]
        fn reads_always_pass_and_read_only_lets_nothing_else(
            rules in proptest::collection::vec(any_rule(), 0..3),
            read_only in any::<bool>(),
            unit in any::<u8>(),
            pdu in any_pdu(),
        ) {
            let p = Policy { read_only, write: rules.clone() };
            let got = p.permits(unit, &pdu);
            if function::only_reads(&pdu) {
                prop_assert_eq!(got, Ok(()));
            } else if read_only {
                prop_assert_eq!(got, Err(Why::ReadOnly));
            } else {
                let any = rules.is_empty() || rules.iter().any(|r| model(r, unit, &pdu));
                prop_assert_eq!(got.is_ok(), any);
            }
        }
    }
}
