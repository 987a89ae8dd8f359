//! `mbgate wire A B` (docs/simulator.md, "A virtual line"): two pseudo-terminals joined
//! like a null-modem cable, where each byte takes its time on the wire at its sender's
//! baud rate and arrives as the receiver's UART would take it. The bits and their
//! timing are `uart.rs`'s (pure); the ptys `pty.rs`'s; here the thin loop between them.

pub mod pty;
pub(crate) mod uart;

use crate::line::port::serial::PreciseTimer;
use pty::PtyEnd;
use std::path::PathBuf;
use std::time::Duration;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use uart::{Char, Format, UartReceiver, UartSetting, UartTransmitter};

/// How one end's characters are framed and how fast: `[BAUD,]FORMAT`, FORMAT `8N1`,
/// `8E1`... or `auto`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct EndSpec {
    /// A baud rate fixed here, whatever the program on the end sets.
    pub(crate) baud: Option<u32>,
    /// The format; `None`: `auto`, from the termios hints.
    pub(crate) format: Option<Format>,
}

/// An end's spec that is not `[BAUD,]FORMAT` or `auto`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub(crate) enum BadSpec {
    /// The baud rate.
    #[error("{0:?}: a baud rate is a number above 0")]
    Baud(String),
    /// The format.
    #[error(transparent)]
    Format(#[from] uart::BadFormat),
}

impl std::str::FromStr for EndSpec {
    type Err = BadSpec;

    fn from_str(s: &str) -> Result<EndSpec, BadSpec> {
        let (baud, format) = match s.split_once(',') {
            Some((b, f)) => (Some(b), f),
            None if s.bytes().all(|c| c.is_ascii_digit()) => (Some(s), ""),
            None => (None, s),
        };
        let baud = baud
            .map(|b| match b.parse::<u32>() {
                Ok(n) if n > 0 => Ok(n),
                _ => Err(BadSpec::Baud(b.to_owned())),
            })
            .transpose()?;
        let format = match format {
            "" => Some(Format::N81),
            "auto" => None,
            f => Some(f.parse()?),
        };
        Ok(EndSpec { baud, format })
    }
}

/// `mbgate wire`'s options (its flags are `crate::cli`'s).
#[derive(Debug, Clone)]
pub(crate) struct WireOptions {
    /// The paths to make for the ends (symbolic links to their ptys, removed at exit).
    pub(crate) paths: [PathBuf; 2],
    /// Each end's format.
    pub(crate) specs: [EndSpec; 2],
    /// The share of characters lost on the wire, 0 to 1.
    pub(crate) loss: f64,
    /// The share of characters with one bit flipped on the wire, 0 to 1.
    pub(crate) noise: f64,
    /// RS-232 echo: each end hears what it sends too.
    pub(crate) echo: bool,
    /// The seed of loss and noise.
    pub(crate) seed: u64,
}

/// Why the line could not run.
#[derive(Debug, thiserror::Error)]
pub(crate) enum WireError {
    /// A bad option.
    #[error("{0}")]
    Option(String),
    /// An end could not be made.
    #[error("cannot make {path}: {source}")]
    Make {
        /// The link asked for.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// Reading or writing a pty failed.
    #[error("{0}")]
    Io(#[from] std::io::Error),
}

/// Counts of one direction, said at the end.
#[derive(Debug, Default, Clone, Copy)]
struct Counts {
    sent: u64,
    delivered: u64,
    lost: u64,
    /// Delivered bytes the receiving program's pty had no room for.
    overflow: u64,
}

/// Runs the line until `shutdown`.
pub(crate) async fn run(args: &WireOptions, shutdown: CancellationToken) -> Result<(), WireError> {
    for (name, p) in [("--loss", args.loss), ("--noise", args.noise)] {
        if !(0.0..=1.0).contains(&p) {
            return Err(WireError::Option(format!(
                "{name} {p}: a share from 0 to 1"
            )));
        }
    }
    let paths = [&args.paths[0], &args.paths[1]];
    let mut ends = Vec::new();
    for p in paths {
        ends.push(PtyEnd::open(p).map_err(|source| WireError::Make {
            path: p.clone(),
            source,
        })?);
    }
    say_ready(args, &ends);
    let base = Instant::now();
    let mut wire = Wire {
        args,
        specs: [args.specs[0], args.specs[1]],
        ends,
        base,
        tx: [UartTransmitter::default(), UartTransmitter::default()],
        rx: [UartReceiver::new(), UartReceiver::new()],
        counts: [Counts::default(), Counts::default()],
        rng: fastrand::Rng::with_seed(args.seed),
    };
    let mut timer = PreciseTimer::new()?;
    let mut wake: Option<u64> = None;
    let mut buf = vec![0u8; 4096];
    loop {
        let deadline = wake.map(|w| base + Duration::from_nanos(w));
        let from = tokio::select! {
            _ = shutdown.cancelled() => break,
            r = wire.ends[0].master.readable() => { r?.clear_ready(); Some(0) }
            r = wire.ends[1].master.readable() => { r?.clear_ready(); Some(1) }
            r = timer.until(deadline.unwrap_or(base)), if deadline.is_some() => { r?; None }
        };
        if let Some(i) = from {
            wire.send(i, &mut buf)?;
        }
        wake = wire.deliver()?;
    }
    wire.say_counts();
    Ok(())
}

/// The line's two ends and settings, as said when it is ready.
fn say_ready(args: &WireOptions, ends: &[PtyEnd]) {
    let show = |s: EndSpec| {
        let f = s.format.map_or("auto".to_string(), |f| f.to_string());
        match s.baud {
            Some(b) => format!("{b} baud {f}"),
            None => format!("{f}, the baud rate its program sets"),
        }
    };
    eprintln!(
        "mbgate wire: {} ({}, {}) <-> {} ({}, {}){}{}{}: ready",
        args.paths[0].display(),
        ends[0].device.display(),
        show(args.specs[0]),
        args.paths[1].display(),
        ends[1].device.display(),
        show(args.specs[1]),
        if args.loss > 0.0 {
            format!(", loss {}", args.loss)
        } else {
            String::new()
        },
        if args.noise > 0.0 {
            format!(", noise {}", args.noise)
        } else {
            String::new()
        },
        if args.echo { ", echo" } else { "" },
    );
}

/// The line's state between its two ends: each direction's UARTs and counts.
struct Wire<'a> {
    args: &'a WireOptions,
    specs: [EndSpec; 2],
    ends: Vec<PtyEnd>,
    /// Time zero of the UARTs' nanoseconds.
    base: Instant,
    tx: [UartTransmitter; 2],
    rx: [UartReceiver; 2],
    counts: [Counts; 2],
    rng: fastrand::Rng,
}

impl Wire<'_> {
    /// Each direction's counts, said at the end.
    fn say_counts(&self) {
        for (i, c) in self.counts.iter().enumerate() {
            eprintln!(
                "mbgate wire: {} -> {}: {} bytes sent, {} lost, {} delivered{}",
                self.args.paths[i].display(),
                self.args.paths[1 - i].display(),
                c.sent,
                c.lost,
                c.delivered,
                if c.overflow > 0 {
                    format!(", {} not taken (its program did not read)", c.overflow)
                } else {
                    String::new()
                }
            );
        }
    }

    fn ns(&self, t: Instant) -> u64 {
        (t - self.base).as_nanos() as u64
    }

    /// End `i`'s setting: the spec's, else what its program set.
    fn setting(&self, i: usize) -> std::io::Result<(UartSetting, uart::ErrorHandling)> {
        let seen = self.ends[i].seen()?;
        let baud = self.specs[i].baud.unwrap_or(seen.baud).max(1);
        let format = self.specs[i].format.unwrap_or(seen.hinted);
        Ok((UartSetting { baud, format }, seen.handling))
    }

    /// Puts on the wire everything end `i`'s program has written, up to the buffer;
    /// the next round reads the rest (readiness is cleared only after a short read).
    fn send(&mut self, i: usize, buf: &mut [u8]) -> Result<(), WireError> {
        loop {
            let n = match self.ends[i].read(buf) {
                Ok(n) => n,
                Err(e) if e.raw_os_error() == Some(libc::EIO) => 0,
                Err(e) => return Err(e.into()),
            };
            if n == 0 {
                break;
            }
            let now = self.ns(Instant::now());
            let (sent_at, _) = self.setting(i)?;
            let starts = self.tx[i].schedule(now, n, sent_at);
            for (&b, start) in buf[..n].iter().zip(starts) {
                let c = Char::new(start, b, sent_at);
                self.counts[i].sent += 1;
                match uart::disturb(c, self.args.loss, self.args.noise, &mut self.rng) {
                    Some(d) => self.rx[1 - i].push(d),
                    None => self.counts[i].lost += 1,
                }
                if self.args.echo {
                    self.rx[i].push(c);
                }
            }
            if n < buf.len() {
                break;
            }
        }
        Ok(())
    }

    /// Hands each end what has arrived by now; when the next character arrives.
    fn deliver(&mut self) -> Result<Option<u64>, WireError> {
        let now = self.ns(Instant::now());
        let mut wake: Option<u64> = None;
        for j in 0..2 {
            let (heard_at, handling) = self.setting(j)?;
            let (arrivals, next) = self.rx[j].poll(now, heard_at);
            if !arrivals.is_empty() {
                let mut out = Vec::with_capacity(arrivals.len());
                for a in arrivals {
                    handling.deliver(a.what, &mut out);
                }
                let took = self.ends[j].write(&out).unwrap_or(0);
                // Counted against the other end, whose bytes these mostly are.
                self.counts[1 - j].delivered += took as u64;
                self.counts[1 - j].overflow += (out.len() - took) as u64;
            }
            wake = match (wake, next) {
                (Some(a), Some(b)) => Some(a.min(b)),
                (a, b) => a.or(b),
            };
        }
        Ok(wake)
    }
}

#[cfg(test)]
mod tests;
