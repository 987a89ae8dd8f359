//! `mbgate wire A B` (docs/simulator.md, "A virtual line"): two pseudo-terminals joined
//! like a null-modem cable, where each byte takes its time on the wire at its sender's
//! baud rate and arrives as the receiver's UART would take it. The bits and their
//! timing are `uart.rs`'s (pure); the ptys `pty.rs`'s; here the thin loop between them.

pub(crate) mod pty;
pub mod uart;

use crate::port::serial::PreciseTimer;
use pty::PtyEnd;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use uart::{Char, Format, UartReceiver, UartSetting, UartTransmitter};

/// How one end's characters are framed and how fast: `[BAUD,]FORMAT`, FORMAT `8N1`,
/// `8E1`... or `auto`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EndSpec {
    /// A baud rate fixed here, whatever the program on the end sets.
    pub baud: Option<u32>,
    /// The format; `None`: `auto`, from the termios hints.
    pub format: Option<Format>,
}

impl std::str::FromStr for EndSpec {
    type Err = String;

    fn from_str(s: &str) -> Result<EndSpec, String> {
        let (baud, format) = match s.split_once(',') {
            Some((b, f)) => (Some(b), f),
            None if s.bytes().all(|c| c.is_ascii_digit()) => (Some(s), ""),
            None => (None, s),
        };
        let baud = baud
            .map(|b| match b.parse::<u32>() {
                Ok(n) if n > 0 => Ok(n),
                _ => Err(format!("{b:?}: a baud rate is a number above 0")),
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

/// `mbgate wire`'s options.
#[derive(Debug, clap::Args)]
pub struct WireArgs {
    /// End A: the path to make (a symbolic link to its pty, removed at exit).
    #[arg(value_name = "A")]
    pub a_path: PathBuf,
    /// End B: likewise.
    #[arg(value_name = "B")]
    pub b_path: PathBuf,
    /// Both ends' format, FORMAT or BAUD,FORMAT: 8N1, 8E1, 8O1, 8N2, 7E1...; or
    /// `auto`: the parity and stop bits the program set, where a pty still shows them
    /// (PARODD: odd; INPCK without it: even, as serialport and so mbgate set it;
    /// pyserial's even parity reads as none). A baud rate given here is used whatever
    /// the program sets; otherwise each end's speed is the one its program set.
    #[arg(long, value_name = "[BAUD,]FORMAT", default_value = "8N1")]
    pub format: EndSpec,
    /// End A's format, as --format (which it overrides).
    #[arg(long = "a", value_name = "[BAUD,]FORMAT")]
    pub a_spec: Option<EndSpec>,
    /// End B's format, as --format (which it overrides).
    #[arg(long = "b", value_name = "[BAUD,]FORMAT")]
    pub b_spec: Option<EndSpec>,
    /// The share of characters lost on the wire, 0 to 1 (the receiver hears an idle
    /// line for them).
    #[arg(long, default_value_t = 0.0, value_name = "P")]
    pub loss: f64,
    /// The share of characters with one bit flipped on the wire, 0 to 1 (any bit:
    /// a data bit, the parity bit, the start or a stop bit).
    #[arg(long, default_value_t = 0.0, value_name = "P")]
    pub noise: f64,
    /// RS-232 echo: each end hears what it sends too (as it left, before loss and
    /// noise), as a 2-wire RS-485 transceiver or a loopback adapter does.
    #[arg(long)]
    pub echo: bool,
    /// The seed of loss and noise: the same seed, the same faults for the same bytes.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

/// Why the line could not run.
#[derive(Debug, thiserror::Error)]
pub enum WireError {
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

/// `mbgate wire`: exit code 0 when stopped by a signal, 1 when it failed, 2 bad options.
pub fn main(args: WireArgs) -> ExitCode {
    let rt = match crate::runtime::for_command(ExitCode::FAILURE) {
        Ok(rt) => rt,
        Err(code) => return code,
    };
    let shutdown = CancellationToken::new();
    let r = rt.block_on(async {
        let stop = shutdown.clone();
        tokio::spawn(async move {
            use tokio::signal::unix::{signal, SignalKind};
            let (Ok(mut term), Ok(mut int)) = (
                signal(SignalKind::terminate()),
                signal(SignalKind::interrupt()),
            ) else {
                return;
            };
            tokio::select! {
                _ = term.recv() => {}
                _ = int.recv() => {}
            }
            stop.cancel();
        });
        run(&args, shutdown).await
    });
    match r {
        Ok(()) => ExitCode::SUCCESS,
        Err(WireError::Option(e)) => {
            eprintln!("mbgate: {e}");
            ExitCode::from(2)
        }
        Err(e) => {
            eprintln!("mbgate: {e}");
            ExitCode::FAILURE
        }
    }
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
pub async fn run(args: &WireArgs, shutdown: CancellationToken) -> Result<(), WireError> {
    for (name, p) in [("--loss", args.loss), ("--noise", args.noise)] {
        if !(0.0..=1.0).contains(&p) {
            return Err(WireError::Option(format!(
                "{name} {p}: a share from 0 to 1"
            )));
        }
    }
    let specs = [
        args.a_spec.unwrap_or(args.format),
        args.b_spec.unwrap_or(args.format),
    ];
    let paths = [&args.a_path, &args.b_path];
    let mut ends = Vec::new();
    for p in paths {
        ends.push(PtyEnd::open(p).map_err(|source| WireError::Make {
            path: p.clone(),
            source,
        })?);
    }
    let show = |s: EndSpec| {
        let f = s.format.map_or("auto".to_string(), |f| f.to_string());
        match s.baud {
            Some(b) => format!("{b} baud {f}"),
            None => format!("{f}, the baud rate its program sets"),
        }
    };
    eprintln!(
        "mbgate wire: {} ({}, {}) <-> {} ({}, {}){}{}{}: ready",
        paths[0].display(),
        ends[0].device.display(),
        show(specs[0]),
        paths[1].display(),
        ends[1].device.display(),
        show(specs[1]),
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
    let base = Instant::now();
    let ns = |t: Instant| (t - base).as_nanos() as u64;
    let setting =
        |i: usize, ends: &[PtyEnd]| -> std::io::Result<(UartSetting, uart::ErrorHandling)> {
            let seen = ends[i].seen()?;
            let baud = specs[i].baud.unwrap_or(seen.baud).max(1);
            let format = specs[i].format.unwrap_or(seen.hinted);
            Ok((UartSetting { baud, format }, seen.handling))
        };
    let mut tx = [UartTransmitter::default(), UartTransmitter::default()];
    let mut rx = [UartReceiver::new(), UartReceiver::new()];
    let mut counts = [Counts::default(), Counts::default()];
    let mut rng = fastrand::Rng::with_seed(args.seed);
    let mut timer = PreciseTimer::new()?;
    let mut wake: Option<u64> = None;
    let mut buf = vec![0u8; 4096];
    loop {
        let deadline = wake.map(|w| base + Duration::from_nanos(w));
        let from = tokio::select! {
            _ = shutdown.cancelled() => break,
            r = ends[0].master.readable() => { r?.clear_ready(); Some(0) }
            r = ends[1].master.readable() => { r?.clear_ready(); Some(1) }
            r = timer.until(deadline.unwrap_or(base)), if deadline.is_some() => { r?; None }
        };
        if let Some(i) = from {
            // Everything the program has written, up to the buffer; the next round
            // reads the rest (readiness is cleared only after a short read).
            loop {
                let n = match ends[i].read(&mut buf) {
                    Ok(n) => n,
                    Err(e) if e.raw_os_error() == Some(libc::EIO) => 0,
                    Err(e) => return Err(e.into()),
                };
                if n == 0 {
                    break;
                }
                let now = ns(Instant::now());
                let (sent_at, _) = setting(i, &ends)?;
                let starts = tx[i].schedule(now, n, sent_at);
                for (&b, start) in buf[..n].iter().zip(starts) {
                    let c = Char::new(start, b, sent_at);
                    counts[i].sent += 1;
                    match uart::disturb(c, args.loss, args.noise, &mut rng) {
                        Some(d) => rx[1 - i].push(d),
                        None => counts[i].lost += 1,
                    }
                    if args.echo {
                        rx[i].push(c);
                    }
                }
                if n < buf.len() {
                    break;
                }
            }
        }
        let now = ns(Instant::now());
        wake = None;
        for j in 0..2 {
            let (heard_at, handling) = setting(j, &ends)?;
            let (arrivals, next) = rx[j].poll(now, heard_at);
            if !arrivals.is_empty() {
                let mut out = Vec::with_capacity(arrivals.len());
                for a in arrivals {
                    handling.deliver(a.what, &mut out);
                }
                let took = ends[j].write(&out).unwrap_or(0);
                // Counted against the other end, whose bytes these mostly are.
                counts[1 - j].delivered += took as u64;
                counts[1 - j].overflow += (out.len() - took) as u64;
            }
            wake = match (wake, next) {
                (Some(a), Some(b)) => Some(a.min(b)),
                (a, b) => a.or(b),
            };
        }
    }
    for (i, c) in counts.iter().enumerate() {
        eprintln!(
            "mbgate wire: {} -> {}: {} bytes sent, {} lost, {} delivered{}",
            paths[i].display(),
            paths[1 - i].display(),
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
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn end_specs_parse() {
        let s: EndSpec = "9600,8E1".parse().unwrap();
        assert_eq!(s.baud, Some(9600));
        assert_eq!(s.format.unwrap().to_string(), "8E1");
        let s: EndSpec = "auto".parse().unwrap();
        assert_eq!(
            s,
            EndSpec {
                baud: None,
                format: None
            }
        );
        let s: EndSpec = "19200".parse().unwrap();
        assert_eq!(s.format, Some(Format::N81));
        assert!("0,8N1".parse::<EndSpec>().is_err());
        assert!("9600,9X9".parse::<EndSpec>().is_err());
    }
}
