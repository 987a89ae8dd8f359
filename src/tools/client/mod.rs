//! The master client: `mbgate read` and `mbgate write` answer the field
//! engineer's first question, "does the device answer?".
//!
//! One request of the common function codes (01, 02, 03, 04, 05, 06, 0F, 10, 17;
//! docs/protocol.md §1) goes to a gateway over Modbus/TCP, or straight to a device on a
//! serial port in the CIE-M10's serial Modbus/TCP mode (whole MBAP frames on the line,
//! no CRC; docs/protocol.md §3). The decoded reply or exception is printed; `--poll` repeats
//! it, `-v` shows both frames as hex.
//!
//! - Over TCP, replies are delimited by the strict decoder (docs/design.md §1 step 1); a
//!   frame with another transaction id (a late answer to an earlier poll) is ignored.
//! - On a serial line, which can lose bytes (docs/protocol.md §3), replies are found by the
//!   resynchronising decoder (docs/design.md §2) with a judge that accepts only the answer
//!   to the outstanding request: its transaction id, its unit id and the shape the
//!   request calls for.
//!
//! How it ended ([`Outcome`]) is `crate::cli`'s to make an exit code of.

mod transport;

use transport::Exchange;
pub(crate) use transport::{ClientTransport, Master};

use crate::frame::hex::Hex;
use crate::frame::request::{exception_name, Reply};
use crate::frame::Adu;
use std::io;
use std::time::{Duration, SystemTime};

/// How a request ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Outcome {
    /// A normal response.
    Reply,
    /// No answer: timeout, connection refused, port missing, or no valid reply.
    NoAnswer,
    /// The device (or the gateway) answered with an exception.
    Exception,
}

/// A session's options (`mbgate read` and `write`'s flags, `crate::cli`'s).
#[derive(Debug, Clone)]
pub(crate) struct Session {
    /// The unit id asked.
    pub(crate) unit: u8,
    /// How long each request waits for its reply, in ms.
    pub(crate) timeout_ms: u64,
    /// Poll every this many ms (none: once).
    pub(crate) poll: Option<u64>,
    /// Stop polling after this many requests.
    pub(crate) count: Option<u64>,
    /// Print both frames as hex.
    pub(crate) verbose: bool,
}

/// A line on stdout; a closed stdout (`| head`) is not an error worth a panic.
fn say(line: std::fmt::Arguments<'_>) {
    use std::io::Write as _;
    let _ = writeln!(io::stdout(), "{line}");
}

/// Round trips of a polling session, for the summary.
#[derive(Default)]
struct Tally {
    polls: u64,
    replies: u64,
    exceptions: u64,
    failures: u64,
    min: Option<Duration>,
    max: Duration,
    sum: Duration,
}

impl Tally {
    fn add(&mut self, code: Outcome, rtt: Option<Duration>) {
        self.polls += 1;
        match code {
            Outcome::Reply => self.replies += 1,
            Outcome::Exception => self.exceptions += 1,
            _ => self.failures += 1,
        }
        if let Some(rtt) = rtt {
            self.min = Some(self.min.map_or(rtt, |m| m.min(rtt)));
            self.max = self.max.max(rtt);
            self.sum += rtt;
        }
    }

    fn summary(&self) -> String {
        let mut s = format!(
            "--- {} requests: {} replies, {} exceptions, {} unanswered",
            self.polls, self.replies, self.exceptions, self.failures
        );
        let answered = self.replies + self.exceptions;
        if let (Some(min), true) = (self.min, answered > 0) {
            s += &format!(
                "; round trip min/avg/max {}/{}/{} ms",
                millis(min),
                millis(self.sum / answered as u32),
                millis(self.max)
            );
        }
        s
    }
}

fn millis(d: Duration) -> String {
    format!("{:.1}", d.as_secs_f64() * 1000.0)
}

/// One request, or one per `--poll` period until `--count` or `stop`. Returns how the
/// last request ended.
pub(crate) async fn session(
    common: &Session,
    transport: ClientTransport,
    pdu: &[u8],
    stop: tokio_util::sync::CancellationToken,
) -> Outcome {
    let mut master = Master::new(transport, Duration::from_millis(common.timeout_ms));
    let Some(period) = common.poll else {
        return once(&mut master, common, pdu, None).await.0;
    };
    let mut ticker = tokio::time::interval(Duration::from_millis(period));
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let ctrl_c = stop.cancelled();
    tokio::pin!(ctrl_c);
    let mut tally = Tally::default();
    let mut last = Outcome::NoAnswer;
    while common.count.is_none_or(|n| tally.polls < n) {
        tokio::select! {
            _ = ticker.tick() => {}
            _ = &mut ctrl_c => break,
        }
        let stamp = SystemTime::now();
        tokio::select! {
            (code, rtt) = once(&mut master, common, pdu, Some(stamp)) => {
                tally.add(code, rtt);
                last = code;
            }
            _ = &mut ctrl_c => break,
        }
    }
    say(format_args!("{}", tally.summary()));
    last
}

/// Sends one request and prints the outcome: with `-v` both frames, then a status line
/// (timestamped when polling), then the values. Returns how it ended and the round
/// trip, if answered.
async fn once(
    master: &mut Master,
    common: &Session,
    pdu: &[u8],
    stamp: Option<SystemTime>,
) -> (Outcome, Option<Duration>) {
    let request = Adu::build(master.next_tid(), common.unit, pdu);
    let outcome = master.transact(&request).await;
    let prefix = stamp
        .map(|t| format!("{} ", utc_stamp(t)))
        .unwrap_or_default();
    let tx = || {
        if common.verbose {
            say(format_args!(
                "tx {}",
                Hex(&master.transport().wire(&request))
            ));
        }
    };
    let x = match outcome {
        Ok(x) => x,
        Err(e) => {
            if stamp.is_some() {
                say(format_args!("{prefix}{e}"));
            } else {
                eprintln!("mbgate: {e}");
            }
            tx();
            return (Outcome::NoAnswer, None);
        }
    };
    let rtt = millis(x.round_trip);
    let code = match x.decoded {
        Reply::Exception { function, code } => {
            say(format_args!(
                "{prefix}exception 0x{:02X} {} (fc 0x{:02X}) in {rtt} ms",
                code.get(),
                exception_name(code.get()),
                function.get()
            ));
            Outcome::Exception
        }
        _ => {
            say(format_args!("{prefix}reply in {rtt} ms"));
            Outcome::Reply
        }
    };
    tx();
    if common.verbose {
        say_received(master, &x);
    }
    for line in value_lines(&x.decoded) {
        say(format_args!("{line}"));
    }
    (code, Some(x.round_trip))
}

/// With `-v`: the frames that were not the reply, the bytes skipped, and the reply.
fn say_received(master: &Master, x: &Exchange) {
    for f in &x.ignored {
        say(format_args!(
            "rx {} (transaction id {:#06x} is not ours: ignored)",
            Hex(f.as_bytes()),
            f.tid()
        ));
    }
    if x.dropped_bytes > 0 {
        say(format_args!(
            "rx skipped {} bytes that were not the reply",
            x.dropped_bytes
        ));
    }
    say(format_args!(
        "rx {}",
        Hex(&master.transport().wire(&x.reply))
    ));
}

/// `ADDR: VALUE (0xHEX)` for registers, `ADDR: 1` / `ADDR: 0` for bits, one a line.
fn value_lines(reply: &Reply) -> Vec<String> {
    let register = |addr: u16, v: u16| format!("{addr}: {v} (0x{v:04X})");
    let bit = |addr: u16, b: bool| format!("{addr}: {}", u8::from(b));
    match reply {
        Reply::Bits { addr, values } => values
            .iter()
            .zip(*addr..=u16::MAX)
            .map(|(&b, a)| bit(a, b))
            .collect(),
        Reply::Registers { addr, values } => values
            .iter()
            .zip(*addr..=u16::MAX)
            .map(|(&v, a)| register(a, v))
            .collect(),
        Reply::WroteCoil { addr, value } => vec![bit(*addr, *value)],
        Reply::WroteRegister { addr, value } => vec![register(*addr, *value)],
        Reply::WroteMany { addr, qty, coils } => {
            let what = match (coils, qty) {
                (true, 1) => "coil",
                (true, _) => "coils",
                (false, 1) => "register",
                (false, _) => "registers",
            };
            let last = u32::from(*addr) + u32::from(*qty).max(1) - 1;
            let at = if *qty <= 1 {
                format!("at {addr}")
            } else {
                format!("at {addr}..={last}")
            };
            vec![format!("wrote {qty} {what} {at}")]
        }
        Reply::Raw { data } => vec![format!("data {}", Hex(data))],
        Reply::Exception { .. } => Vec::new(),
    }
}

/// `2025-06-01T10:00:00.123Z`: UTC, millisecond resolution.
fn utc_stamp(t: SystemTime) -> String {
    humantime::format_rfc3339_millis(t).to_string()
}

#[cfg(test)]
mod tests;
