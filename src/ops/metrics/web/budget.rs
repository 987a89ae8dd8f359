//! How much password checking the metrics listener does (docs/watching.md "Behind TLS
//! and a password"): a bcrypt check is CPU by design, so a flood of wrong logins must
//! not turn into a flood of it. Each source (an IPv4 address, or an IPv6 /64) may
//! have [`LoginBudget::BURST`] checks at once, then one every
//! [`LoginBudget::EVERY`]; all sources together may spend [`LoginBudget::SHARE`] of a
//! core on checks, measured, with [`LoginBudget::CPU_BURST`] in hand. A login past
//! either is refused without a check. Successful logins are remembered elsewhere
//! (`login.rs`) and need no check, so Prometheus, once in, spends none of it. Plain
//! data, time passed in.

use crate::access::source_of;
use std::collections::HashMap;
use std::net::IpAddr;
use std::time::Duration;
use tokio::time::Instant;

/// A bucket of checks that refills with time.
#[derive(Debug, Clone, Copy)]
struct Bucket {
    /// Checks in hand (fractions are a check on its way).
    tokens: f64,
    at: Instant,
}

/// The checks each source, and all of them, may still make.
#[derive(Debug)]
pub(crate) struct LoginBudget {
    sources: HashMap<IpAddr, Bucket>,
    /// Shared by the sources that found the table full.
    others: Bucket,
    /// Seconds of CPU the checks may still spend (below zero after a check that
    /// cost more than was in hand: none until it is paid back).
    cpu: f64,
    cpu_at: Instant,
}

impl LoginBudget {
    /// Checks a source may make at once.
    pub(crate) const BURST: f64 = 5.0;
    /// Then one a source every so often.
    pub(crate) const EVERY: Duration = Duration::from_secs(5);
    /// The part of a core all checks together may take, measured.
    pub(crate) const SHARE: f64 = 0.1;
    /// CPU time in hand for checks when nothing was spent for a while.
    pub(crate) const CPU_BURST: Duration = Duration::from_secs(1);
    /// Sources remembered; past it, new sources share one bucket.
    pub(crate) const SOURCES: usize = 1024;

    pub(crate) fn new(now: Instant) -> Self {
        LoginBudget {
            sources: HashMap::new(),
            others: Bucket {
                tokens: Self::BURST,
                at: now,
            },
            cpu: Self::CPU_BURST.as_secs_f64(),
            cpu_at: now,
        }
    }

    fn refill(b: &mut Bucket, now: Instant) {
        let secs = now.saturating_duration_since(b.at).as_secs_f64();
        b.tokens = (b.tokens + secs / Self::EVERY.as_secs_f64()).min(Self::BURST);
        b.at = now;
    }

    fn refill_cpu(&mut self, now: Instant) {
        let secs = now.saturating_duration_since(self.cpu_at).as_secs_f64();
        self.cpu = (self.cpu + secs * Self::SHARE).min(Self::CPU_BURST.as_secs_f64());
        self.cpu_at = now;
    }

    /// May `ip` have a password checked at `now`? If so the check is taken from its
    /// budget; if not, how long until it may.
    pub(crate) fn take(&mut self, ip: IpAddr, now: Instant) -> Result<(), Duration> {
        self.refill_cpu(now);
        let source = source_of(ip);
        if !self.sources.contains_key(&source) && self.sources.len() >= Self::SOURCES {
            // Forget the sources that have their whole budget back.
            self.sources.retain(|_, b| {
                Self::refill(b, now);
                b.tokens < Self::BURST
            });
        }
        let room = self.sources.len() < Self::SOURCES;
        let bucket = if self.sources.contains_key(&source) || room {
            self.sources.entry(source).or_insert(Bucket {
                tokens: Self::BURST,
                at: now,
            })
        } else {
            &mut self.others
        };
        Self::refill(bucket, now);
        let own_wait = if bucket.tokens >= 1.0 {
            Duration::ZERO
        } else {
            Self::EVERY.mul_f64(1.0 - bucket.tokens)
        };
        let cpu_wait = if self.cpu > 0.0 {
            Duration::ZERO
        } else {
            Duration::from_secs_f64(-self.cpu / Self::SHARE)
        };
        let wait = own_wait.max(cpu_wait);
        if wait > Duration::ZERO {
            return Err(wait.max(Duration::from_secs(1)));
        }
        bucket.tokens -= 1.0;
        Ok(())
    }

    /// A check took `took` of CPU.
    pub(crate) fn spent(&mut self, took: Duration, now: Instant) {
        self.refill_cpu(now);
        self.cpu -= took.as_secs_f64();
    }

    /// Sources remembered now.
    #[cfg(test)]
    fn remembered(&self) -> usize {
        self.sources.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn ip(s: &str) -> IpAddr {
        s.parse().unwrap()
    }

    #[test]
    fn a_source_has_its_burst_then_one_check_every_so_often() {
        let t0 = Instant::now();
        let mut b = LoginBudget::new(t0);
        let a = ip("192.0.2.7");
        for _ in 0..5 {
            assert_eq!(b.take(a, t0), Ok(()));
        }
        assert_eq!(b.take(a, t0), Err(LoginBudget::EVERY));
        // Another source, and an IPv6 host's neighbour in its /64 shares its budget.
        assert_eq!(b.take(ip("192.0.2.8"), t0), Ok(()));
        let v6 = ip("2001:db8::1");
        for _ in 0..5 {
            assert_eq!(b.take(v6, t0), Ok(()));
        }
        assert!(b.take(ip("2001:db8::2"), t0).is_err());
        assert!(
            b.take(ip("::ffff:192.0.2.7"), t0).is_err(),
            "the mapped address is the IPv4 one"
        );
        let later = t0 + LoginBudget::EVERY;
        assert_eq!(b.take(a, later), Ok(()));
        assert!(b.take(a, later).is_err());
    }

    #[test]
    fn all_sources_together_spend_a_share_of_a_core() {
        let t0 = Instant::now();
        let mut b = LoginBudget::new(t0);
        // Checks of 0.3 s each from ever new sources: the second of CPU in hand goes
        // in four (the fourth takes it below zero), then it is paid back at the share.
        let mut t = t0;
        let mut done = 0;
        for i in 0..100u32 {
            let src = IpAddr::V4((0x0A00_0000 + i).into());
            if b.take(src, t).is_ok() {
                done += 1;
                b.spent(Duration::from_millis(300), t);
            }
        }
        assert_eq!(done, 4);
        let wait = b.take(ip("10.1.0.0"), t).unwrap_err();
        assert_eq!(
            wait,
            Duration::from_secs(2),
            "0.2 s owed at a tenth of a core"
        );
        t += wait;
        assert_eq!(b.take(ip("10.1.0.0"), t), Ok(()));
    }

    proptest! {
        /// However the logins come (sources, times, check costs), the checks made in
        /// any span of time stay within the budget: per source its burst and one per
        /// EVERY, and in all at most the share of a core plus what was in hand, plus
        /// the one check that took it below zero.
        #[test]
        fn the_budget_holds_whatever_the_logins(
            logins in proptest::collection::vec((0u8..8, 0u64..3_000, 1u64..400), 1..400)
        ) {
            let t0 = Instant::now();
            let mut b = LoginBudget::new(t0);
            let mut t = t0;
            let mut per = HashMap::<u8, u32>::new();
            let (mut cpu, mut max_check) = (0.0f64, 0.0f64);
            for (src, gap_ms, cost_ms) in logins {
                t += Duration::from_millis(gap_ms);
                if b.take(IpAddr::V4([10, 0, 0, src].into()), t).is_ok() {
                    *per.entry(src).or_default() += 1;
                    let cost = Duration::from_millis(cost_ms);
                    b.spent(cost, t);
                    cpu += cost.as_secs_f64();
                    max_check = max_check.max(cost.as_secs_f64());
                }
            }
            let secs = (t - t0).as_secs_f64();
            for n in per.values() {
                prop_assert!(f64::from(*n) <= LoginBudget::BURST + secs / LoginBudget::EVERY.as_secs_f64() + 1e-9);
            }
            prop_assert!(cpu <= LoginBudget::CPU_BURST.as_secs_f64() + secs * LoginBudget::SHARE + max_check + 1e-9);
        }
    }

    #[test]
    fn the_table_of_sources_is_bounded() {
        let t0 = Instant::now();
        let mut b = LoginBudget::new(t0);
        for i in 0..3 * LoginBudget::SOURCES as u32 {
            let _ = b.take(IpAddr::V4((0x0A00_0000 + i).into()), t0);
            // Each check cheap: the CPU budget is not what limits here.
            b.spent(Duration::ZERO, t0);
        }
        assert_eq!(b.remembered(), LoginBudget::SOURCES);
        // The sources past the table share one bucket: its burst, then nothing.
        let shared = (0..100u32)
            .filter(|i| b.take(IpAddr::V4((0x0B00_0000 + i).into()), t0).is_ok())
            .count();
        assert_eq!(
            shared, 0,
            "the shared bucket was spent by the earlier overflow"
        );
        // Once the remembered sources have their budget back they are forgotten.
        let later = t0 + LoginBudget::EVERY.mul_f64(LoginBudget::BURST);
        assert_eq!(b.take(ip("10.200.0.1"), later), Ok(()));
        assert_eq!(b.remembered(), 1);
    }
}
