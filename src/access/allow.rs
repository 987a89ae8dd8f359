//! Which source addresses a listener takes (docs/security.md "Allow lists"): addresses
//! and CIDR blocks, IPv4 and IPv6, an IPv4 master seen on a dual-stack socket as an
//! IPv4-mapped IPv6 address (`::ffff:10.0.0.5`) judged as the IPv4 address it is; and
//! the rate-limited log of refused sources. Plain data, time passed in.

use std::collections::HashMap;
use std::fmt;
use std::net::IpAddr;
use std::str::FromStr;
use std::time::{Duration, Instant};

/// The source a budget or a log counts by: an IPv4 address (an IPv4-mapped one as the
/// IPv4 address it is), or an IPv6 /64, which one host is commonly given whole.
pub(crate) fn source_of(ip: IpAddr) -> IpAddr {
    match ip.to_canonical() {
        IpAddr::V6(v6) => IpAddr::V6((u128::from(v6) & !u128::from(u64::MAX)).into()),
        v4 => v4,
    }
}

/// One entry of an allow list: an address and how many of its leading bits must match
/// (32 or 128 for a single address). Held in canonical form: an IPv4-mapped IPv6 block
/// (`::ffff:10.0.0.0/104`) is stored as the IPv4 block it covers (`10.0.0.0/8`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Net {
    addr: IpAddr,
    prefix: u8,
}

impl Net {
    /// Does `ip` (canonical) fall in this block?
    fn contains(&self, ip: IpAddr) -> bool {
        match (self.addr, ip) {
            (IpAddr::V4(net), IpAddr::V4(ip)) => {
                let mask = u32::MAX
                    .checked_shl(32 - u32::from(self.prefix))
                    .unwrap_or(0);
                u32::from(net) & mask == u32::from(ip) & mask
            }
            (IpAddr::V6(net), IpAddr::V6(ip)) => {
                let mask = u128::MAX
                    .checked_shl(128 - u32::from(self.prefix))
                    .unwrap_or(0);
                u128::from(net) & mask == u128::from(ip) & mask
            }
            // An IPv6 block shorter than /96 that covers the IPv4-mapped range
            // (`::/0`, `::/80`) takes the IPv4 masters a dual-stack listener sees in it:
            // what someone who writes `::/0` means is "everyone".
            (IpAddr::V6(_), IpAddr::V4(ip)) => self.contains(IpAddr::V6(ip.to_ipv6_mapped())),
            (IpAddr::V4(_), IpAddr::V6(_)) => false,
        }
    }

    fn max_prefix(addr: IpAddr) -> u8 {
        if addr.is_ipv4() {
            32
        } else {
            128
        }
    }
}

/// Why a text is no address or block.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub(crate) enum NetError {
    /// Neither an address nor an address and a prefix length.
    #[error("expected an address or a CIDR block like 10.0.0.0/24 or 2001:db8::/32, got {0:?}")]
    NotAnAddress(String),
    /// The prefix length is past the address's bits.
    #[error("{given:?}: the prefix length must be 0 to {max}")]
    Prefix {
        /// The text as given.
        given: String,
        /// The address's bits: 32 or 128.
        max: u8,
    },
    /// The address has bits set past its prefix length: it names no block.
    #[error("{given:?} has bits set past its prefix length: did you mean \"{block}\"?")]
    HostBits {
        /// The text as given.
        given: String,
        /// The block it would be, those bits cleared.
        block: Net,
    },
}

impl FromStr for Net {
    type Err = NetError;

    /// `10.0.0.0/24`, `2001:db8::/32`, `127.0.0.1`, `::1`. A block whose address has
    /// bits set past its prefix is refused (it names no block: `10.0.0.1/24` is
    /// `10.0.0.0/24` or a typo), with the block it would be.
    fn from_str(s: &str) -> Result<Net, NetError> {
        let t = s.trim();
        let (addr, prefix) = match t.split_once('/') {
            Some((a, p)) => (a, Some(p)),
            None => (t, None),
        };
        let bad = || NetError::NotAnAddress(s.to_owned());
        let addr: IpAddr = addr.parse().map_err(|_| bad())?;
        let max = Net::max_prefix(addr);
        let prefix = match prefix {
            None => max,
            Some(p) => match p.parse::<u8>() {
                Ok(p) if p <= max => p,
                _ => {
                    let given = s.to_owned();
                    return Err(NetError::Prefix { given, max });
                }
            },
        };
        let mut net = Net { addr, prefix };
        // An IPv4-mapped block is the IPv4 block it covers (a /96 or longer).
        if let IpAddr::V6(v6) = addr {
            if let Some(v4) = v6.to_ipv4_mapped() {
                if prefix >= 96 {
                    net = Net {
                        addr: IpAddr::V4(v4),
                        prefix: prefix - 96,
                    };
                }
            }
        }
        let masked = Net {
            addr: masked(net.addr, net.prefix),
            ..net
        };
        if masked != net {
            return Err(NetError::HostBits {
                given: s.to_owned(),
                block: masked,
            });
        }
        Ok(net)
    }
}

/// `addr` with the bits past `prefix` cleared.
fn masked(addr: IpAddr, prefix: u8) -> IpAddr {
    match addr {
        IpAddr::V4(a) => {
            let mask = u32::MAX.checked_shl(32 - u32::from(prefix)).unwrap_or(0);
            IpAddr::V4((u32::from(a) & mask).into())
        }
        IpAddr::V6(a) => {
            let mask = u128::MAX.checked_shl(128 - u32::from(prefix)).unwrap_or(0);
            IpAddr::V6((u128::from(a) & mask).into())
        }
    }
}

impl fmt::Display for Net {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.prefix == Net::max_prefix(self.addr) {
            write!(f, "{}", self.addr)
        } else {
            write!(f, "{}/{}", self.addr, self.prefix)
        }
    }
}

/// A listener's `allow`: the sources it takes. Never empty (the file's reader refuses
/// `allow = []`, which would refuse everyone); no list at all means everyone.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AllowList(Vec<Net>);

impl AllowList {
    /// The list of `nets`, in the order given.
    pub(crate) fn new(nets: Vec<Net>) -> AllowList {
        AllowList(nets)
    }

    /// Is a master connecting from `ip` taken? An IPv4-mapped IPv6 source is judged as
    /// its IPv4 address.
    pub(crate) fn allows(&self, ip: IpAddr) -> bool {
        let ip = ip.to_canonical();
        self.0.iter().any(|n| n.contains(ip))
    }

    /// The entries, as the file writes them.
    pub(crate) fn nets(&self) -> &[Net] {
        &self.0
    }
}

impl fmt::Display for AllowList {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let all: Vec<String> = self.0.iter().map(Net::to_string).collect();
        f.write_str(&all.join(", "))
    }
}

/// The log of refused sources: each source is named at its first refusal, then at most
/// once per `EVERY` with the count of refusals in between, so a scanner
/// or a misconfigured master retrying in a loop cannot flood the journal. At most
/// `SOURCES` sources are remembered; past that, refusals from new
/// sources are told together, once per period.
/// Keyed by source address, or by whatever else a caller counts apart (a source and a
/// reason).
#[derive(Debug)]
pub(crate) struct RefusedLog<K = IpAddr> {
    sources: HashMap<K, RefusedSource>,
    /// Refusals from sources not remembered (the table full), since last told.
    others: u64,
    others_told: Option<Instant>,
}

#[derive(Debug)]
struct RefusedSource {
    told: Instant,
    /// Refusals since it was last told.
    since: u64,
}

/// What to log for one refusal.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Tell {
    /// Nothing: this source was told of recently.
    Quiet,
    /// Name the source; `more` refusals of it went untold since the last time.
    Source { more: u64 },
    /// The table is full: `count` refusals from sources not named, since last told.
    Others { count: u64 },
}

impl<K> Default for RefusedLog<K> {
    fn default() -> Self {
        RefusedLog {
            sources: HashMap::new(),
            others: 0,
            others_told: None,
        }
    }
}

impl<K: std::hash::Hash + Eq> RefusedLog<K> {
    /// The least time between two lines about one source.
    pub(crate) const EVERY: Duration = Duration::from_secs(60);
    /// The most sources remembered.
    pub(crate) const SOURCES: usize = 1024;

    /// A connection from `ip` was refused at `now`: what to say about it.
    pub(crate) fn refused(&mut self, ip: K, now: Instant) -> Tell {
        let due = |t: Instant| now.saturating_duration_since(t) >= Self::EVERY;
        if let Some(seen) = self.sources.get_mut(&ip) {
            if due(seen.told) {
                let more = seen.since;
                *seen = RefusedSource {
                    told: now,
                    since: 0,
                };
                return Tell::Source { more };
            }
            seen.since += 1;
            return Tell::Quiet;
        }
        if self.sources.len() >= Self::SOURCES {
            // Forget the sources whose period is over; if none is, count this one
            // with the others.
            self.sources.retain(|_, s| !due(s.told));
        }
        if self.sources.len() >= Self::SOURCES {
            self.others += 1;
            if self.others_told.is_none_or(due) {
                self.others_told = Some(now);
                let count = std::mem::take(&mut self.others);
                return Tell::Others { count };
            }
            return Tell::Quiet;
        }
        let seen = RefusedSource {
            told: now,
            since: 0,
        };
        self.sources.insert(ip, seen);
        Tell::Source { more: 0 }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn list(nets: &[&str]) -> AllowList {
        AllowList::new(nets.iter().map(|n| n.parse().unwrap()).collect())
    }

    fn ip(s: &str) -> IpAddr {
        s.parse().unwrap()
    }

    #[test]
    fn addresses_and_blocks_of_both_families_and_mapped_addresses() {
        let l = list(&["10.0.0.0/24", "2001:db8::/32", "127.0.0.1", "::1"]);
        for yes in [
            "10.0.0.0",
            "10.0.0.255",
            "127.0.0.1",
            "2001:db8::5",
            "2001:db8:ffff::1",
            "::1",
        ] {
            assert!(l.allows(ip(yes)), "{yes}");
        }
        for no in [
            "10.0.1.0",
            "9.255.255.255",
            "127.0.0.2",
            "2001:db9::1",
            "::2",
            "0.0.0.0",
        ] {
            assert!(!l.allows(ip(no)), "{no}");
        }
        // A dual-stack listener sees an IPv4 master as ::ffff:a.b.c.d.
        assert!(l.allows(ip("::ffff:10.0.0.7")));
        assert!(l.allows(ip("::ffff:127.0.0.1")));
        assert!(!l.allows(ip("::ffff:127.0.0.2")));
        // A mapped block in the list is the IPv4 block it covers.
        let mapped = list(&["::ffff:192.168.0.0/112"]);
        assert_eq!(mapped.to_string(), "192.168.0.0/16");
        assert!(mapped.allows(ip("192.168.3.4")) && mapped.allows(ip("::ffff:192.168.3.4")));
        assert!(!mapped.allows(ip("192.169.0.1")));
        // 0.0.0.0/0 takes every IPv4 address; ::/0 every address, an IPv4 master
        // on a dual-stack listener (::ffff:a.b.c.d) included.
        let any4 = list(&["0.0.0.0/0"]);
        assert!(any4.allows(ip("203.0.113.9")) && !any4.allows(ip("2001:db8::1")));
        assert!(any4.allows(ip("::ffff:203.0.113.9")));
        let any6 = list(&["::/0"]);
        assert!(any6.allows(ip("2001:db8::1")) && any6.allows(ip("10.0.0.1")));
        assert!(any6.allows(ip("::ffff:10.0.0.1")));
        // A block that does not cover the mapped range takes no IPv4 master.
        let doc = list(&["2001:db8::/32", "::/96"]);
        assert!(!doc.allows(ip("10.0.0.1")) && !doc.allows(ip("::ffff:10.0.0.1")));
        assert!(list(&["::/80"]).allows(ip("::ffff:10.0.0.1")));
    }

    #[test]
    fn a_bad_entry_is_refused_saying_why() {
        let e = "10.0.0.1/24".parse::<Net>().unwrap_err();
        let block = "10.0.0.0/24".parse().unwrap();
        assert!(matches!(&e, NetError::HostBits { block: b, .. } if *b == block));
        assert!(
            e.to_string().contains("did you mean \"10.0.0.0/24\""),
            "{e}"
        );
        let e = "10.0.0.0/33".parse::<Net>().unwrap_err();
        assert!(matches!(e, NetError::Prefix { max: 32, .. }), "{e}");
        assert!(e.to_string().contains("0 to 32"), "{e}");
        let e = "2001:db8::/129".parse::<Net>().unwrap_err();
        assert!(e.to_string().contains("0 to 128"), "{e}");
        for bad in [
            "",
            "10.0.0",
            "host.example",
            "10.0.0.0/",
            "10.0.0.0/x",
            "/8",
        ] {
            assert!(bad.parse::<Net>().is_err(), "{bad:?}");
        }
        assert_eq!(
            " 10.1.0.0/16 ".parse::<Net>().unwrap().to_string(),
            "10.1.0.0/16"
        );
    }

    #[test]
    fn each_source_is_told_once_a_period_with_the_count_between() {
        let mut log: RefusedLog = RefusedLog::default();
        let t0 = Instant::now();
        let (a, b) = (ip("192.0.2.1"), ip("192.0.2.2"));
        assert_eq!(log.refused(a, t0), Tell::Source { more: 0 });
        assert_eq!(log.refused(b, t0), Tell::Source { more: 0 });
        for i in 1..=5 {
            assert_eq!(log.refused(a, t0 + Duration::from_secs(i)), Tell::Quiet);
        }
        let later = t0 + RefusedLog::<IpAddr>::EVERY;
        assert_eq!(log.refused(a, later), Tell::Source { more: 5 });
        assert_eq!(log.refused(a, later), Tell::Quiet);
        assert_eq!(log.refused(b, later), Tell::Source { more: 0 });
    }

    #[test]
    fn past_the_table_new_sources_are_told_together() {
        let mut log: RefusedLog = RefusedLog::default();
        let t0 = Instant::now();
        for i in 0..RefusedLog::<IpAddr>::SOURCES as u32 {
            let src = IpAddr::V4((0x0A00_0000 + i).into());
            assert_eq!(log.refused(src, t0), Tell::Source { more: 0 });
        }
        let new = |i: u32| IpAddr::V4((0x0B00_0000 + i).into());
        assert_eq!(log.refused(new(0), t0), Tell::Others { count: 1 });
        for i in 1..100 {
            assert_eq!(log.refused(new(i), t0), Tell::Quiet);
        }
        assert!(log.sources.len() <= RefusedLog::<IpAddr>::SOURCES);
        // A period on, the old sources are forgotten and new ones named again.
        let later = t0 + RefusedLog::<IpAddr>::EVERY;
        assert_eq!(log.refused(new(200), later), Tell::Source { more: 0 });
    }
}
