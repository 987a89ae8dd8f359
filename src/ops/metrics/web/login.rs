//! The users of the metrics listener and the check of a login (docs/watching.md
//! "Behind TLS and a password"): HTTP Basic authentication against the bcrypt hashes
//! of the web configuration file (`basic_auth_users`), as Prometheus' exporter-toolkit
//! does it.
//!
//! - A failed login costs the same whether the user exists or not: an unknown user's
//!   password is checked against a hash of the users' highest cost, and the user is
//!   found by comparing keyed tags of every name, with no early exit.
//! - A password that checked is remembered, as a tag keyed by a secret of this
//!   process (HMAC-SHA-256, never the password), until the file is read again: a
//!   scrape every 15 s costs one bcrypt check, not one a scrape.
//! - Every other check waits for the one before it ([`Logins::check`]), at a low
//!   priority, within each source's budget and all sources' (`budget.rs`); each refused
//!   login is logged once a minute per source with the count (`RefusedLog`).

use super::budget::LoginBudget;
use crate::access::allow::{RefusedLog, Tell};
use base64::Engine as _;
use ring::hmac;
use std::net::IpAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::Semaphore;
use tracing::warn;

/// `bcrypt::hash(.., 4)` of a password nobody is told.
const DUMMY_AT_COST_4: &str = "$2b$04$TuX7z591qOck7WYcO3DxRufkOQfv37p9txwvBcR2BI9scRjl8/1mK";

/// The users of a web configuration file, and the passwords that checked.
#[derive(Debug)]
pub(crate) struct Users {
    key: hmac::Key,
    /// Each user's name, as a tag.
    names: Vec<hmac::Tag>,
    hashes: Vec<String>,
    /// What an unknown user's password is checked against: no password matches it.
    dummy: String,
    /// Each user's password that checked, as a tag.
    checked: Mutex<Vec<Option<hmac::Tag>>>,
}

impl Users {
    /// `users`: each name and its bcrypt hash, checked already (`cost` its cost).
    pub(crate) fn new(users: &[(String, String, u32)]) -> Users {
        let rng = ring::rand::SystemRandom::new();
        let key = hmac::Key::generate(hmac::HMAC_SHA256, &rng).expect("the system's randomness");
        let cost = users.iter().map(|u| u.2).max().unwrap_or(10);
        // A hash made at cost 4 with the cost written as the users' highest: checking
        // a password against it takes that cost, and no password matches it.
        let dummy = format!("$2y${cost:02}${}", &DUMMY_AT_COST_4[7..]);
        Users {
            names: users
                .iter()
                .map(|u| hmac::sign(&key, u.0.as_bytes()))
                .collect(),
            hashes: users.iter().map(|u| u.1.clone()).collect(),
            checked: Mutex::new(vec![None; users.len()]),
            dummy,
            key,
        }
    }

    pub(crate) fn len(&self) -> usize {
        self.hashes.len()
    }

    /// The user named `name`: every name compared, in constant time each, whichever
    /// matches.
    fn find(&self, name: &[u8]) -> Option<usize> {
        let mut found = None;
        for (i, tag) in self.names.iter().enumerate() {
            if hmac::verify(&self.key, name, tag.as_ref()).is_ok() {
                found = Some(i);
            }
        }
        found
    }

    /// Did `password` of user `i` check before?
    fn remembered(&self, i: Option<usize>, password: &[u8]) -> bool {
        let Some(i) = i else { return false };
        let checked = self.checked.lock().expect("not poisoned");
        checked[i]
            .as_ref()
            .is_some_and(|tag| hmac::verify(&self.key, password, tag.as_ref()).is_ok())
    }

    fn remember(&self, i: usize, password: &[u8]) {
        let tag = hmac::sign(&self.key, password);
        self.checked.lock().expect("not poisoned")[i] = Some(tag);
    }

    /// The hash `password` of user `i` is checked against (an unknown user's: the
    /// dummy).
    fn hash(&self, i: Option<usize>) -> String {
        i.map_or_else(|| self.dummy.clone(), |i| self.hashes[i].clone())
    }
}

/// The user and password of an `Authorization: Basic ...` header's value.
pub(crate) fn basic(value: &str) -> Option<(Vec<u8>, Vec<u8>)> {
    let (scheme, rest) = value.trim().split_once(' ')?;
    if !scheme.eq_ignore_ascii_case("basic") {
        return None;
    }
    let bytes = base64::engine::general_purpose::STANDARD
        .decode(rest.trim())
        .ok()?;
    let colon = bytes.iter().position(|&b| b == b':')?;
    Some((bytes[..colon].to_vec(), bytes[colon + 1..].to_vec()))
}

/// How a login went.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Login {
    /// Known user, right password: the user.
    Ok(String),
    /// No credentials, or wrong ones.
    Refused,
    /// Refused without a check: the source (or all of them) checked too many lately;
    /// it may try again after this long.
    TooMany(Duration),
}

/// The checks of the listener: one at a time, within the budgets, the refusals logged.
#[derive(Debug)]
pub(crate) struct Logins {
    one: Semaphore,
    budget: Mutex<LoginBudget>,
    refused: Mutex<RefusedLog>,
}

impl Default for Logins {
    fn default() -> Self {
        Logins {
            one: Semaphore::new(1),
            budget: Mutex::new(LoginBudget::new(tokio::time::Instant::now())),
            refused: Mutex::new(RefusedLog::default()),
        }
    }
}

impl Logins {
    /// The login of `authorization` (the header's value, if any) from `peer`, against
    /// `users`.
    pub(crate) async fn check(
        &self,
        users: &Arc<Users>,
        authorization: Option<&str>,
        peer: IpAddr,
    ) -> Login {
        // No credentials at all: a browser's first request, nothing to check or say.
        let Some(value) = authorization else {
            return Login::Refused;
        };
        let Some((name, password)) = basic(value) else {
            self.refused(peer, "not Basic credentials");
            return Login::Refused;
        };
        let user = users.find(&name);
        if users.remembered(user, &password) {
            return Login::Ok(String::from_utf8_lossy(&name).into_owned());
        }
        let taken = self
            .budget
            .lock()
            .expect("not poisoned")
            .take(peer, tokio::time::Instant::now());
        if let Err(wait) = taken {
            self.refused(peer, "too many logins, not checked");
            return Login::TooMany(wait);
        }
        let hash = users.hash(user);
        let Ok(_one) = self.one.acquire().await else {
            return Login::Refused;
        };
        let (checked, took) = tokio::task::spawn_blocking(move || {
            let started = cpu_time();
            let ok = bcrypt::verify(&password, &hash).unwrap_or(false);
            (ok.then_some(password), cpu_time().saturating_sub(started))
        })
        .await
        .unwrap_or((None, Duration::ZERO));
        self.budget
            .lock()
            .expect("not poisoned")
            .spent(took, tokio::time::Instant::now());
        match (user, checked) {
            (Some(i), Some(password)) => {
                users.remember(i, &password);
                Login::Ok(String::from_utf8_lossy(&name).into_owned())
            }
            _ => {
                self.refused(peer, "wrong user or password");
                Login::Refused
            }
        }
    }

    /// A login from `peer` refused: said once a minute per source with the count.
    fn refused(&self, peer: IpAddr, why: &str) {
        let tell = self
            .refused
            .lock()
            .expect("not poisoned")
            .refused(peer.to_canonical(), std::time::Instant::now());
        match tell {
            Tell::Quiet => {}
            Tell::Source { more: 0 } => warn!(
                "metrics listener: login from {peer} refused: {why} (said once a minute per source)"
            ),
            Tell::Source { more } => warn!(
                "metrics listener: login from {peer} refused: {why} ({more} more from it in the last minute)"
            ),
            Tell::Others { count } => warn!(
                "metrics listener: {count} logins refused from sources too many to name each, in the last minute"
            ),
        }
    }
}

/// The CPU time this thread has used (a bcrypt check's cost, whatever else the machine
/// does).
fn cpu_time() -> Duration {
    let ns = std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse::<u64>().ok());
    ns.map_or(Duration::ZERO, Duration::from_nanos)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `htpasswd -nbBC 4 alice secret` and `... bob hunter2`.
    fn users() -> Arc<Users> {
        Arc::new(Users::new(&[
            ("alice".into(), bcrypt::hash("secret", 4).unwrap(), 4),
            ("bob".into(), bcrypt::hash("hunter2", 4).unwrap(), 4),
        ]))
    }

    fn header(user: &str, password: &str) -> String {
        let b = base64::engine::general_purpose::STANDARD.encode(format!("{user}:{password}"));
        format!("Basic {b}")
    }

    #[test]
    fn basic_credentials() {
        assert_eq!(
            basic("Basic YWxpY2U6czpl"),
            Some((b"alice".to_vec(), b"s:e".to_vec()))
        );
        assert_eq!(
            basic("basic  YWxpY2U6 "),
            Some((b"alice".to_vec(), Vec::new()))
        );
        assert_eq!(basic("Bearer YWxpY2U6czpl"), None);
        assert_eq!(basic("Basic !!!"), None);
        assert_eq!(basic("Basic YWxpY2U="), None, "no colon");
    }

    proptest::proptest! {
        /// Whatever a peer puts in the header, reading it is an answer, never a panic;
        /// credentials a client encodes read back as they were (the password may hold
        /// colons, the user not).
        #[test]
        fn any_header_reads_and_credentials_round_trip(
            junk in ".{0,200}",
            user in "[^:]{0,20}",
            password in proptest::collection::vec(proptest::num::u8::ANY, 0..80),
        ) {
            let _ = basic(&junk);
            let _ = basic(&format!("Basic {junk}"));
            let mut raw = user.as_bytes().to_vec();
            raw.push(b':');
            raw.extend(&password);
            let value = format!("Basic {}", base64::engine::general_purpose::STANDARD.encode(&raw));
            proptest::prop_assert_eq!(basic(&value), Some((user.into_bytes(), password)));
        }
    }

    #[tokio::test]
    async fn right_wrong_unknown_and_remembered() {
        let (u, logins) = (users(), Logins::default());
        let peer: IpAddr = "192.0.2.1".parse().unwrap();
        let check = |h: Option<String>| {
            let (u, logins) = (u.clone(), &logins);
            async move { logins.check(&u, h.as_deref(), peer).await }
        };
        assert_eq!(check(None).await, Login::Refused);
        assert_eq!(check(Some(header("alice", "nope"))).await, Login::Refused);
        assert_eq!(check(Some(header("carol", "secret"))).await, Login::Refused);
        assert_eq!(
            check(Some(header("alice", "secret"))).await,
            Login::Ok("alice".into())
        );
        assert_eq!(
            check(Some(header("bob", "hunter2"))).await,
            Login::Ok("bob".into())
        );
        // Four checks of the source's five made; a remembered password needs none.
        for _ in 0..10 {
            assert_eq!(
                check(Some(header("alice", "secret"))).await,
                Login::Ok("alice".into())
            );
        }
        // Alice's remembered password lets no other in: checked, the fifth.
        assert_eq!(check(Some(header("alice", "secreT"))).await, Login::Refused);
        assert!(matches!(
            check(Some(header("bob", "x"))).await,
            Login::TooMany(_)
        ));
        // Past the budget, the remembered passwords still need no check.
        assert_eq!(
            check(Some(header("bob", "hunter2"))).await,
            Login::Ok("bob".into())
        );
        assert!(!u.remembered(Some(0), b"secreT"));
        assert!(!u.remembered(None, b"secret"));
    }

    #[test]
    fn an_unknown_user_is_checked_against_a_hash_of_the_highest_cost() {
        let u = Users::new(&[
            ("a".into(), bcrypt::hash("x", 4).unwrap(), 4),
            ("b".into(), bcrypt::hash("y", 5).unwrap(), 5),
        ]);
        let dummy = u.hash(None);
        assert!(dummy.starts_with("$2y$05$"), "{dummy}");
        assert!(!bcrypt::verify("", &dummy).unwrap());
        assert!(!bcrypt::verify("x", &dummy).unwrap());
        assert_eq!(u.find(b"b"), Some(1));
        assert_eq!(u.find(b"c"), None);
    }
}
