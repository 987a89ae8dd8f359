//! `mbgate scan` (docs/scan.md): what is on a bus. Tries baud rates, formats, framings
//! and unit ids on a serial port, or unit ids on a Modbus/TCP address, with reads only,
//! and says what answered, with a ready `[[line]]` block. What is sent and judged is
//! `probe.rs`'s (pure); the port's side `serial.rs`'s and `tcp.rs`'s; the report's
//! text `report.rs`'s; here the options and the loop over settings.

mod listen;
pub(crate) mod probe;
mod report;
mod serial;
pub(crate) mod sniff;
mod tcp;

pub(crate) use report::{json, table};

use probe::{Heard, SerialFraming, UnitList};
use std::io::IsTerminal;
use std::time::{Duration, Instant};
use tokio_util::sync::CancellationToken;

use crate::tools::wire::uart::Format;

/// `mbgate scan`'s options (its flags are `crate::cli`'s).
#[derive(Debug, Clone)]
pub(crate) struct ScanOptions {
    /// The serial port (or a virtual line's end) to scan.
    pub(crate) port: Option<String>,
    /// Scan a Modbus/TCP device or gateway at HOST:PORT instead: unit ids only.
    pub(crate) tcp: Option<String>,
    /// The baud rates to try, in order [default: 19200,9600,115200,38400,57600,4800,2400,1200]
    pub(crate) baud: Vec<u32>,
    /// The formats to try, in order [default: 8E1,8N1,8N2,8O1]
    pub(crate) format: Vec<Format>,
    /// The framings to try, in order [default: rtu,ascii]
    pub(crate) framing: Vec<SerialFraming>,
    /// The unit ids to try: ids and ranges, `1-247`, `1,2,10-20`.
    pub(crate) units: UnitList,
    /// How long a device may take to answer, beyond the request's and the reply's own
    /// time on the wire (a later reply still counts, in the next units' time).
    pub(crate) timeout_ms: u64,
    /// Leave a setting after this many units got no frame with a good CRC or LRC (a
    /// setting that got one is scanned to the last unit; so are 19200 and 9600 baud,
    /// 8E1 and 8N1, RTU and ASCII, the settings most buses use).
    pub(crate) give_up: usize,
    /// Go on to the other settings after one is found (a bus has one setting, so by
    /// default the scan ends with the first that answers).
    pub(crate) all: bool,
    /// Send nothing: listen to a live bus at each setting in turn and report the
    /// setting, units, function codes, request rate and reply times heard.
    pub(crate) listen: bool,
    /// With --listen: how long to listen at each setting.
    pub(crate) listen_secs: f64,
    /// Print the result as JSON instead of a table.
    pub(crate) json: bool,
}

/// Why a scan could not run.
#[derive(Debug, thiserror::Error)]
pub(crate) enum ScanError {
    /// A bad option.
    #[error("{0}")]
    Option(String),
    /// The port could not be opened (held by a gateway, absent...).
    #[error("cannot open {path}: {source}")]
    Open {
        /// The port.
        path: String,
        /// Why: names the process that holds it, when one does.
        source: tokio_serial::Error,
    },
    /// Reading or writing failed.
    #[error("{0}")]
    Io(#[from] std::io::Error),
}

/// A baud rate, format and framing.
pub(crate) type SerialSetting = (u32, Format, SerialFraming);

/// A unit that answered.
#[derive(Debug, Clone)]
pub(crate) struct Found {
    /// Its id.
    pub(crate) unit: u8,
    /// Its setting (none on TCP).
    pub(crate) serial: Option<(u32, Format, SerialFraming)>,
    /// What it answered to the read.
    pub(crate) answered: String,
    /// Its read device identification objects, or why none.
    pub(crate) device_id: Result<Vec<(u8, String)>, probe::NoIdentity>,
    /// Its report server id data, or why none.
    pub(crate) server_id: Result<Vec<u8>, probe::NoIdentity>,
    /// Its reply times: from the request's last byte on the line to the reply's
    /// first, each reply of its own that came in its window.
    pub(crate) replies: Vec<Duration>,
    /// How long into the scan it was found.
    pub(crate) after: Duration,
}

/// Reads of one register asked of each unit found, besides the first and its two
/// identity requests, so that its reply time has a median of at least a few.
pub(crate) const TIMED_READS: usize = 3;

impl Found {
    /// Keeps the reply time of `heard` when it is this unit's frame.
    pub(crate) fn timed(&mut self, heard: &Heard, replied: Option<Duration>) {
        if let (Heard::Frame { unit, .. }, Some(t)) = (heard, replied) {
            if *unit == self.unit {
                self.replies.push(t);
            }
        }
    }

    /// The median and the longest of its reply times, if any came.
    pub(crate) fn reply_time(&self) -> Option<(Duration, Duration)> {
        let mut t = self.replies.clone();
        t.sort();
        Some((*t.get(t.len() / 2)?, *t.last()?))
    }
}

/// What a scan found, and how it went.
#[derive(Debug, Default)]
pub(crate) struct Report {
    /// The units that answered.
    pub(crate) found: Vec<Found>,
    /// Settings where bytes came but no frame with a good check.
    pub(crate) garbage: Vec<(u32, Format, SerialFraming)>,
    /// Settings where whole frames with a good check came that answered no request:
    /// the first one's unit and function code.
    pub(crate) unanswering: Vec<(SerialSetting, (u8, u8))>,
    /// What ended a `--tcp` scan's connection, when the peer closed it.
    pub(crate) closed: Option<String>,
    /// Ctrl-C ended it early.
    pub(crate) interrupted: bool,
    /// How long it took.
    pub(crate) elapsed: Duration,
    /// Tries made.
    pub(crate) tries: usize,
}

/// What a scan found: with `--listen`, what was heard; else the report.
pub(crate) enum Scanned {
    Heard(listen::Overheard),
    Report(Report),
}

/// `mbgate scan`, until done or `stop` (Ctrl-C: what was found so far).
pub(crate) async fn scan(
    args: &ScanOptions,
    stop: CancellationToken,
) -> Result<Scanned, ScanError> {
    let progress = Progress::new(std::io::stderr().is_terminal() && !args.json);
    if args.listen {
        return listening(args, stop, progress).await.map(Scanned::Heard);
    }
    run(args, stop, progress).await.map(Scanned::Report)
}

impl Scanned {
    /// What is printed (a table, or JSON with `--json`), and whether anything answered.
    pub(crate) fn said(&self, args: &ScanOptions) -> (String, bool) {
        match self {
            Scanned::Heard(heard) => {
                let target = args.port.clone().unwrap_or_default();
                let text = if args.json {
                    format!("{}\n", listen::json(heard, &target))
                } else {
                    listen::table(heard, &target)
                };
                (text, heard.at.is_some())
            }
            Scanned::Report(report) => {
                let target = args.tcp.clone().or(args.port.clone()).unwrap_or_default();
                let tcp = args.tcp.is_some();
                let text = if args.json {
                    format!("{}\n", json(report, &target, tcp))
                } else {
                    table(report, &target, tcp, args)
                };
                (text, !report.found.is_empty())
            }
        }
    }
}

/// The settings `--listen` tries: each baud rate and format once (the wide ones
/// first), every framing judged on what came.
fn settings_of(
    args: &ScanOptions,
) -> Result<(Vec<probe::ProbeSetting>, Vec<SerialSetting>), ScanError> {
    let bauds = if args.baud.is_empty() {
        probe::DEFAULT_BAUDS.to_vec()
    } else {
        args.baud.clone()
    };
    if let Some(b) = bauds.iter().find(|&&b| !(50..=4_000_000).contains(&b)) {
        return Err(ScanError::Option(format!("--baud {b}: 50 to 4000000")));
    }
    let formats: Vec<Format> = if args.format.is_empty() {
        probe::DEFAULT_FORMATS
            .iter()
            .filter_map(|s| s.parse().ok())
            .collect()
    } else {
        args.format.clone()
    };
    if let Some(f) = formats.iter().find(|f| f.data_bits < 7) {
        return Err(ScanError::Option(format!("--format {f}: 7 or 8 data bits")));
    }
    let framings = if args.framing.is_empty() {
        vec![SerialFraming::Rtu, SerialFraming::Ascii]
    } else {
        args.framing.clone()
    };
    let wide: Vec<SerialSetting> = probe::WIDE
        .iter()
        .map(|&(b, f, fr)| (b, f.parse().expect("a format"), fr))
        .filter(|(b, f, fr)| bauds.contains(b) && formats.contains(f) && framings.contains(fr))
        .collect();
    Ok((probe::order(&bauds, &formats, &framings, &wide), wide))
}

async fn listening(
    args: &ScanOptions,
    stop: CancellationToken,
    mut progress: Progress,
) -> Result<listen::Overheard, ScanError> {
    if !(0.1..=3600.0).contains(&args.listen_secs) {
        return Err(ScanError::Option(format!(
            "--listen-secs {}: 0.1 to 3600",
            args.listen_secs
        )));
    }
    let (settings, _) = settings_of(args)?;
    let framings = settings
        .iter()
        .flat_map(|s| s.framings.clone())
        .fold(Vec::new(), |mut v, f| {
            if !v.contains(&f) {
                v.push(f);
            }
            v
        });
    let mut once: Vec<probe::ProbeSetting> = Vec::new();
    for s in settings {
        if !once
            .iter()
            .any(|o| o.baud == s.baud && o.format == s.format)
        {
            once.push(probe::ProbeSetting {
                framings: framings.clone(),
                ..s
            });
        }
    }
    let path = args.port.clone().unwrap_or_default();
    let window = Duration::from_secs_f64(args.listen_secs);
    listen::listen(&path, &once, window, &stop, &mut progress).await
}

/// The scan itself, until done or `stop`.
pub(crate) async fn run(
    args: &ScanOptions,
    stop: CancellationToken,
    mut progress: Progress,
) -> Result<Report, ScanError> {
    let started = Instant::now();
    let timeout = Duration::from_millis(args.timeout_ms);
    let units = args.units.0.clone();
    let mut report = if let Some(addr) = &args.tcp {
        tcp::scan(addr, &units, timeout, &stop, &mut progress).await?
    } else {
        let path = args.port.clone().unwrap_or_default();
        let (settings, wide) = settings_of(args)?;
        serial::scan(
            &path,
            &settings,
            &units,
            args.give_up,
            &wide,
            timeout,
            args.all,
            &stop,
            &mut progress,
        )
        .await?
    };
    progress.done();
    report.interrupted = stop.is_cancelled();
    report.elapsed = started.elapsed();
    Ok(report)
}

/// A unit's identity from the replies to FC 43/14 and FC 17 (either may be nothing).
pub(crate) fn identified(found: &mut Found, device: &Heard, server: &Heard) {
    found.device_id = match device {
        Heard::Frame { pdu, .. } => probe::device_id(pdu),
        _ => Err(probe::NoIdentity::NoAnswer),
    };
    found.server_id = match server {
        Heard::Frame { pdu, .. } => probe::server_id(pdu),
        _ => Err(probe::NoIdentity::NoAnswer),
    };
}

/// The progress bar on stderr, when it is a terminal: tries made and the time left at
/// most, from the tries the give-up rule still allows.
#[derive(Debug)]
pub(crate) struct Progress {
    on: bool,
    started: Instant,
    drawn: bool,
}

impl Progress {
    /// Draws only when `on`.
    pub(crate) fn new(on: bool) -> Progress {
        Progress {
            on,
            started: Instant::now(),
            drawn: false,
        }
    }

    /// `done` tries made of at most `total`, the rest costing `left` at most; `what`
    /// is being tried.
    pub(crate) fn show(&mut self, done: usize, total: usize, left: Duration, what: &str) {
        if !self.on {
            return;
        }
        let width = 30;
        let filled = (done * width).checked_div(total).unwrap_or(0).min(width);
        eprint!(
            "\r[{}{}] {done}/{total} tries, {:.0} s, at most {:.0} s left: {what}\x1b[K",
            "#".repeat(filled),
            " ".repeat(width - filled),
            self.started.elapsed().as_secs_f64(),
            left.as_secs_f64(),
        );
        self.drawn = true;
    }

    fn done(&mut self) {
        if self.drawn {
            eprint!("\r\x1b[K");
        }
    }
}

#[cfg(test)]
mod tests;
