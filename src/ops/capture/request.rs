//! What `mbgate capture` asks the gateway for over the control socket (docs/capture.md
//! "The control socket"): one line of text, `capture` and the filters and stop
//! conditions as `key=value` words; and which packets a filter keeps. Pure.
//!
//! ```text
//! capture line=0 line=tcp unit=3 master=10.0.0.5 function=3 count=100 seconds=60
//! ```
//!
//! Each key may come more than once (any of the values keeps a packet); keys of
//! different names must all hold. Anything else is refused with a message naming it.

use super::packet::Packet;
use std::fmt;
use std::net::{IpAddr, SocketAddr};

/// The longest request line the gateway reads.
pub(crate) const MAX_LINE: usize = 4096;

/// Why a request line, or one of its words, is refused: the message names it.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub(crate) enum BadRequest {
    /// No words.
    #[error("empty request")]
    Empty,
    /// The first word is not a request.
    #[error("unknown request {0:?} (expected capture or reload)")]
    Unknown(String),
    /// A word without `=`.
    #[error("{0:?}: expected key=value")]
    NotKeyValue(String),
    /// A key this request does not have.
    #[error("unknown key {key:?} in {word:?}")]
    UnknownKey {
        /// The key.
        key: String,
        /// The word it is in.
        word: String,
    },
    /// A master that is not an address.
    #[error(
        "master {0:?}: expected an address (10.0.0.5) or an address and port (10.0.0.5:40000)"
    )]
    Master(String),
    /// A number that is not one, or out of its type's range.
    #[error("{key}={value}: not a number in range")]
    Number {
        /// The key.
        key: String,
        /// The value given.
        value: String,
    },
    /// A limit above its most.
    #[error("{key}={value}: at most {max}")]
    TooMuch {
        /// The key.
        key: String,
        /// The value given.
        value: String,
        /// The most.
        max: u64,
    },
    /// A function code out of 1..=127.
    #[error("function={0}: a function code is 1 to 127")]
    Function(String),
    /// A line the gateway does not have.
    #[error("no line {line:?}: the lines are {lines}, and tcp for the TCP side")]
    NoLine {
        /// The line asked for.
        line: String,
        /// The lines there are, `0 (/dev/ttyUSB0), 1 (...)`.
        lines: String,
    },
}

/// A TCP peer to keep: its address, and its port if given.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum MasterMatch {
    Ip(IpAddr),
    Addr(SocketAddr),
}

impl MasterMatch {
    pub(crate) fn parse(s: &str) -> Result<MasterMatch, BadRequest> {
        if let Ok(a) = s.parse::<SocketAddr>() {
            return Ok(MasterMatch::Addr(a));
        }
        let bare = s.trim_start_matches('[').trim_end_matches(']');
        bare.parse::<IpAddr>()
            .map(MasterMatch::Ip)
            .map_err(|_| BadRequest::Master(s.to_owned()))
    }

    fn matches(&self, a: SocketAddr) -> bool {
        let ip = match a.ip() {
            IpAddr::V6(v6) => v6.to_ipv4_mapped().map_or(a.ip(), IpAddr::V4),
            v4 => v4,
        };
        match *self {
            MasterMatch::Ip(want) => ip == want,
            MasterMatch::Addr(want) => ip == want.ip() && a.port() == want.port(),
        }
    }
}

impl fmt::Display for MasterMatch {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            MasterMatch::Ip(ip) => write!(f, "{ip}"),
            MasterMatch::Addr(a) => write!(f, "{a}"),
        }
    }
}

/// A capture as asked for: which packets, and when to stop.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(crate) struct CaptureRequest {
    /// Interfaces to keep, as given: a line's index (`0`), its name (`/dev/ttyUSB0`),
    /// or `tcp` for the TCP side. None: all.
    pub(crate) lines: Vec<String>,
    pub(crate) units: Vec<u8>,
    pub(crate) masters: Vec<MasterMatch>,
    pub(crate) functions: Vec<u8>,
    /// Stop after this many packets.
    pub(crate) count: Option<u64>,
    /// Stop after this many seconds.
    pub(crate) seconds: Option<u64>,
}

/// The longest capture `seconds=` asks for: a year. Past it a deadline would mean
/// nothing (and near `u64::MAX` it cannot be added to a clock).
pub(crate) const MAX_SECONDS: u64 = 366 * 24 * 3600;
/// The most packets `count=` asks for: more than a busy gateway captures in a year.
pub(crate) const MAX_COUNT: u64 = 1_000_000_000_000;

/// A number of `key=` from 1 to `max`; 0 means none (no limit).
fn limit(key: &str, v: &str, max: u64) -> Result<Option<u64>, BadRequest> {
    let n: u64 = number(key, v)?;
    if n > max {
        return Err(BadRequest::TooMuch {
            key: key.to_owned(),
            value: v.to_owned(),
            max,
        });
    }
    Ok(Some(n).filter(|&n| n > 0))
}

/// A number in decimal or, with `0x`, in hex.
fn number<T: TryFrom<u64>>(key: &str, v: &str) -> Result<T, BadRequest> {
    let n = match v.strip_prefix("0x").or_else(|| v.strip_prefix("0X")) {
        Some(hex) => u64::from_str_radix(hex, 16),
        None => v.parse::<u64>(),
    };
    n.ok()
        .and_then(|n| T::try_from(n).ok())
        .ok_or_else(|| BadRequest::Number {
            key: key.to_owned(),
            value: v.to_owned(),
        })
}

impl CaptureRequest {
    /// Reads a request line (without its newline).
    pub(crate) fn parse(line: &str) -> Result<CaptureRequest, BadRequest> {
        let mut words = line.split_ascii_whitespace();
        match words.next() {
            Some("capture") => {}
            Some(w) => return Err(BadRequest::Unknown(w.to_owned())),
            None => return Err(BadRequest::Empty),
        }
        let mut r = CaptureRequest::default();
        for w in words {
            let Some((key, value)) = w.split_once('=') else {
                return Err(BadRequest::NotKeyValue(w.to_owned()));
            };
            match key {
                "line" if !value.is_empty() => r.lines.push(value.to_owned()),
                "unit" => r.units.push(number(key, value)?),
                "master" => r.masters.push(MasterMatch::parse(value)?),
                "function" => {
                    let fc: u8 = number(key, value)?;
                    if fc == 0 || fc >= 0x80 {
                        return Err(BadRequest::Function(value.to_owned()));
                    }
                    r.functions.push(fc);
                }
                "count" => r.count = limit(key, value, MAX_COUNT)?,
                "seconds" => r.seconds = limit(key, value, MAX_SECONDS)?,
                _ => {
                    return Err(BadRequest::UnknownKey {
                        key: key.to_owned(),
                        word: w.to_owned(),
                    })
                }
            }
        }
        Ok(r)
    }

    /// The interfaces this request keeps, among `names` (0: the TCP side, then each
    /// line); an error names a line that is not there.
    pub(crate) fn interfaces(&self, names: &[String]) -> Result<Vec<bool>, BadRequest> {
        if self.lines.is_empty() {
            return Ok(vec![true; names.len()]);
        }
        let mut keep = vec![false; names.len()];
        for l in &self.lines {
            let at = if l == "tcp" {
                Some(0)
            } else if let Ok(i) = l.parse::<usize>() {
                (i + 1 < names.len()).then_some(i + 1)
            } else {
                names.iter().skip(1).position(|n| n == l).map(|i| i + 1)
            };
            let Some(at) = at else {
                let lines: Vec<String> = names
                    .iter()
                    .skip(1)
                    .enumerate()
                    .map(|(i, n)| format!("{i} ({n})"))
                    .collect();
                return Err(BadRequest::NoLine {
                    line: l.clone(),
                    lines: lines.join(", "),
                });
            };
            keep[at] = true;
        }
        Ok(keep)
    }

    /// Does this request keep `p`, whose master (if any) is at `master`? Dropped
    /// bytes and events belong to no known unit or function: the unit and function
    /// filters keep them (on the interfaces kept).
    pub(crate) fn keeps(&self, p: &Packet, master: Option<SocketAddr>) -> bool {
        let any = |v: &[u8], x: Option<u8>| v.is_empty() || x.is_none_or(|x| v.contains(&x));
        if !any(&self.units, p.unit) {
            return false;
        }
        if !any(&self.functions, p.function.map(|f| f & 0x7F)) {
            return false;
        }
        if self.masters.is_empty() {
            return true;
        }
        let peer = p.ends.map(|e| e.client).or(master);
        peer.is_some_and(|a| self.masters.iter().any(|m| m.matches(a)))
    }
}

impl fmt::Display for CaptureRequest {
    /// The request line, as `parse` reads it.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("capture")?;
        for l in &self.lines {
            write!(f, " line={l}")?;
        }
        for u in &self.units {
            write!(f, " unit={u}")?;
        }
        for m in &self.masters {
            write!(f, " master={m}")?;
        }
        for fc in &self.functions {
            write!(f, " function={fc}")?;
        }
        if let Some(n) = self.count {
            write!(f, " count={n}")?;
        }
        if let Some(s) = self.seconds {
            write!(f, " seconds={s}")?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::super::packet::{Dir, Ends, Part, Proto};
    use super::*;

    #[test]
    fn a_request_reads_back_what_it_prints() {
        let r = CaptureRequest::parse(
            "capture line=0 line=tcp unit=3 unit=0x11 master=10.0.0.5 master=[::1]:502 function=0x10 count=5 seconds=9",
        )
        .unwrap();
        assert_eq!(r.units, [3, 17]);
        assert_eq!(r.functions, [16]);
        assert_eq!((r.count, r.seconds), (Some(5), Some(9)));
        assert_eq!(CaptureRequest::parse(&r.to_string()).unwrap(), r);
        assert_eq!(
            CaptureRequest::parse("capture").unwrap(),
            CaptureRequest::default()
        );
    }

    #[test]
    fn a_bad_request_is_refused_naming_what_is_wrong() {
        for (line, says) in [
            ("", "empty"),
            ("status", "unknown request"),
            ("capture unit=300", "unit=300"),
            ("capture function=0", "1 to 127"),
            ("capture function=128", "1 to 127"),
            ("capture master=nowhere", "master \"nowhere\""),
            ("capture colour=red", "unknown key"),
            ("capture unit", "key=value"),
            ("capture seconds=9300000000000000000", "at most 31622400"),
            ("capture seconds=18446744073709551615", "at most 31622400"),
            (
                "capture seconds=18446744073709551616",
                "not a number in range",
            ),
            ("capture seconds=31622401", "at most"),
            ("capture count=1000000000001", "at most 1000000000000"),
            ("capture count=-1", "not a number"),
        ] {
            let e = CaptureRequest::parse(line).unwrap_err().to_string();
            assert!(e.contains(says), "{line}: {e}");
        }
    }

    proptest::proptest! {
        // No failure file in the tree: a case found is kept by hand as a test.
        #![proptest_config(proptest::test_runner::Config { failure_persistence: None, ..Default::default() })]
        /// Whatever a client sends, the gateway answers a request or an error: it
        /// never panics (one client's malformed request closes that client only).
        #[test]
        fn any_line_is_a_request_or_an_error(line in ".{0,200}") {
            let _ = CaptureRequest::parse(&line);
        }

        /// Every request a client can ask for reads back as itself.
        #[test]
        fn every_request_reads_back(
            units in proptest::collection::vec(proptest::num::u8::ANY, 0..4),
            functions in proptest::collection::vec(1u8..0x80, 0..4),
            count in proptest::option::of(1u64..=MAX_COUNT),
            seconds in proptest::option::of(1u64..=MAX_SECONDS),
            port in proptest::option::of(proptest::num::u16::ANY),
        ) {
            let masters = port
                .map(|p| MasterMatch::Addr(SocketAddr::from(([10, 0, 0, 5], p))))
                .into_iter()
                .chain([MasterMatch::Ip([10, 0, 0, 6].into())])
                .collect();
            let r = CaptureRequest { lines: vec!["tcp".into(), "0".into()], units, masters, functions, count, seconds };
            proptest::prop_assert_eq!(CaptureRequest::parse(&r.to_string()), Ok(r));
        }
    }

    #[test]
    fn lines_by_index_name_or_tcp() {
        let names: Vec<String> = ["tcp", "/dev/ttyUSB0", "10.0.0.9:502"]
            .map(String::from)
            .into();
        let pick = |l: &[&str]| {
            let r = CaptureRequest {
                lines: l.iter().map(|s| s.to_string()).collect(),
                ..CaptureRequest::default()
            };
            r.interfaces(&names)
        };
        assert_eq!(pick(&[]), Ok(vec![true, true, true]));
        assert_eq!(pick(&["1"]), Ok(vec![false, false, true]));
        assert_eq!(pick(&["tcp", "/dev/ttyUSB0"]), Ok(vec![true, true, false]));
        let e = pick(&["2"]).unwrap_err().to_string();
        assert!(e.contains("0 (/dev/ttyUSB0), 1 (10.0.0.9:502)"), "{e}");
    }

    #[test]
    fn filters_keep_what_they_name_and_every_drop() {
        let mut tcp = Packet::new(Dir::In, Part::Query, Proto::Mbtcp, vec![]);
        tcp.unit = Some(3);
        tcp.function = Some(0x83);
        tcp.ends = Some(Ends {
            client: "10.0.0.5:40000".parse().unwrap(),
            server: "10.0.0.1:502".parse().unwrap(),
        });
        let only = |s: &str| CaptureRequest::parse(&format!("capture {s}")).unwrap();
        assert!(
            only("unit=3 function=3").keeps(&tcp, None),
            "an exception is its function's"
        );
        assert!(!only("unit=4").keeps(&tcp, None));
        assert!(only("master=10.0.0.5").keeps(&tcp, None));
        assert!(only("master=10.0.0.5:40000").keeps(&tcp, None));
        assert!(!only("master=10.0.0.5:40001").keeps(&tcp, None));
        let mut line = tcp.clone();
        line.ends = None;
        assert!(!only("master=10.0.0.5").keeps(&line, None));
        assert!(only("master=10.0.0.5").keeps(&line, Some("10.0.0.5:1".parse().unwrap())));
        let drop = Packet::new(Dir::In, Part::Other, Proto::Data, vec![0xFF]);
        assert!(only("unit=9 function=16").keeps(&drop, None));
    }
}
