//! `mbgate scan --listen` (docs/scan.md): a live bus heard without a byte sent. Each
//! setting is opened in turn and only read for `--listen-secs`; `sniff.rs` finds the
//! frames in what came; the first setting where most of it is whole frames is the
//! bus's, reported with its units, function codes, request rate and reply times.

use super::probe::{ProbeSetting, SerialFraming};
use super::sniff::{self, Listened, Traffic};
use super::{Progress, ScanError};
use crate::tools::wire::uart::Format;
use std::time::{Duration, Instant};
use tokio::io::AsyncReadExt;
use tokio_serial::SerialStream;
use tokio_util::sync::CancellationToken;

/// What listening found.
#[derive(Debug, Default)]
pub(crate) struct Overheard {
    /// The bus's setting and what it carried, when one was heard.
    pub(super) at: Option<((u32, Format, SerialFraming), Traffic)>,
    /// How long it listened at that setting.
    pub(super) listened: Duration,
    /// Settings listened at.
    pub(super) settings: usize,
    /// Ctrl-C ended it early.
    pub(super) interrupted: bool,
    /// How long it took in all.
    pub(super) elapsed: Duration,
}

/// Listens at each of `settings` for `window`, until a bus is heard (or every
/// setting, with `all` false or not: a bus has one setting). Never writes.
pub(super) async fn listen(
    path: &str,
    settings: &[ProbeSetting],
    window: Duration,
    stop: &CancellationToken,
    progress: &mut Progress,
) -> Result<Overheard, ScanError> {
    let started = Instant::now();
    let mut heard = Overheard::default();
    for (i, s) in settings.iter().enumerate() {
        if stop.is_cancelled() {
            break;
        }
        let left = window * (settings.len() - i) as u32;
        progress.show(
            i,
            settings.len(),
            left,
            &format!("listening at {} {}", s.baud, s.format),
        );
        let mut port =
            crate::line::port::serial::open(&super::serial::config(path, s)).map_err(|source| {
                ScanError::Open {
                    path: path.to_string(),
                    source,
                }
            })?;
        heard.settings += 1;
        let opened = Instant::now();
        let bytes = overhear(&mut port, opened, most_bytes(s, window), window, stop).await?;
        let best = s
            .framings
            .iter()
            .map(|&f| (f, sniff::traffic(f, &bytes)))
            .max_by_key(|(_, t)| t.framed);
        if let Some((framing, traffic)) = best {
            if traffic.heard() {
                heard.listened = opened.elapsed();
                heard.at = Some(((s.baud, s.format, framing), traffic));
                break;
            }
        }
    }
    progress.done();
    heard.interrupted = stop.is_cancelled();
    heard.elapsed = started.elapsed();
    Ok(heard)
}

/// What `port` (opened at `opened`) carries until the window ends, or more came than
/// a wire at this setting carries in it (`most`; a port with no wire, a pty, may give
/// any amount): what came is judged then.
async fn overhear(
    port: &mut SerialStream,
    opened: Instant,
    most: usize,
    window: Duration,
    stop: &CancellationToken,
) -> Result<Listened, ScanError> {
    let mut bytes = Listened::default();
    let mut buf = [0u8; 1024];
    while bytes.len() < most {
        let until = (opened + window).saturating_duration_since(Instant::now());
        if until.is_zero() {
            break;
        }
        tokio::select! {
            r = port.read(&mut buf) => {
                let n = r?;
                if n == 0 {
                    break;
                }
                bytes.push(opened.elapsed(), &buf[..n]);
            }
            _ = tokio::time::sleep(until) => break,
            _ = stop.cancelled() => break,
        }
    }
    Ok(bytes)
}

/// The most bytes listened to at setting `s` for `window`: what its wire carries in
/// that time, and a read's worth more. A live bus at that setting never brings more;
/// a port without a wire (a pty) may bring any amount, and is read no further then.
fn most_bytes(s: &ProbeSetting, window: Duration) -> usize {
    let per_s = f64::from(s.baud) / f64::from(s.format.bits());
    (per_s * window.as_secs_f64()) as usize + 1024
}

/// A duration's median and longest, in whole milliseconds.
fn p50_max(times: &[Duration]) -> Option<(u128, u128)> {
    let mut t = times.to_vec();
    t.sort();
    Some((t.get(t.len() / 2)?.as_millis(), t.last()?.as_millis()))
}

/// The report as a table and a `[[line]]` block; or "nothing heard" and a hint.
pub(super) fn table(h: &Overheard, target: &str) -> String {
    use std::fmt::Write as _;
    let mut s = String::new();
    let Some(((baud, format, framing), t)) = &h.at else {
        let _ = writeln!(
            s,
            "nothing heard on {target} ({:.1} s, {} settings listened at{})",
            h.elapsed.as_secs_f64(),
            h.settings,
            if h.interrupted { ", interrupted" } else { "" }
        );
        let _ = writeln!(
            s,
            "hint: no whole frames with a good check at any setting: is a master polling \
             the bus now? Listen longer (--listen-secs), or check the wiring"
        );
        return s;
    };
    let secs = h.listened.as_secs_f64().max(0.001);
    let _ = writeln!(
        s,
        "heard on {target} at {baud} {format} {} ({:.1} s; {} frames in {secs:.1} s, \
         {:.1} requests/s):",
        framing.name(),
        h.elapsed.as_secs_f64(),
        t.frames,
        t.requests() as f64 / secs
    );
    units_table(&mut s, t);
    let answering: Vec<String> = t
        .units
        .iter()
        .filter(|(_, u)| u.replies > 0)
        .map(|(unit, _)| unit.to_string())
        .collect();
    let _ = writeln!(
        s,
        "\nFor mbgate.toml (in place of the master heard):\n\n[[line]]\nunits = [{}]\n\
         serial = {{ path = \"{target}\", baud_rate = {baud}, data_bits = {}, parity = \"{}\", \
         stop_bits = {}, framing = \"{}\", flow_control = \"none\" }}",
        answering.join(", "),
        format.data_bits,
        super::report::parity_name(format.parity),
        format.stop_bits,
        framing.name()
    );
    s
}

/// A row for each unit heard: its functions, requests, replies, exceptions and reply
/// times.
fn units_table(s: &mut String, t: &Traffic) {
    use std::fmt::Write as _;
    let _ = writeln!(
        s,
        "{:<5} {:<12} {:<9} {:<8} {:<11} reply p50/max",
        "unit", "functions", "requests", "replies", "exceptions"
    );
    for (unit, u) in &t.units {
        let functions: Vec<String> = u.functions.iter().map(|f| format!("{f:02}")).collect();
        let times = match p50_max(&u.times) {
            Some((p50, max)) => format!("{p50}/{max} ms"),
            None => "-".into(),
        };
        let _ = writeln!(
            s,
            "{:<5} {:<12} {:<9} {:<8} {:<11} {times}",
            unit,
            functions.join(","),
            u.requests,
            u.replies,
            u.exceptions
        );
    }
}

/// The report as one JSON object.
pub(super) fn json(h: &Overheard, target: &str) -> String {
    let (setting, units, rate, frames) = match &h.at {
        None => ("null".to_string(), String::new(), 0.0, 0),
        Some(((baud, format, framing), t)) => {
            let units: Vec<String> = t
                .units
                .iter()
                .map(|(unit, u)| {
                    let (p50, max) = match p50_max(&u.times) {
                        Some((a, b)) => (a.to_string(), b.to_string()),
                        None => ("null".into(), "null".into()),
                    };
                    let functions: Vec<String> =
                        u.functions.iter().map(|f| f.to_string()).collect();
                    format!(
                        "{{\"unit\":{unit},\"functions\":[{}],\"requests\":{},\"replies\":{},\"exceptions\":{},\"reply_ms_p50\":{p50},\"reply_ms_max\":{max}}}",
                        functions.join(","),
                        u.requests,
                        u.replies,
                        u.exceptions
                    )
                })
                .collect();
            (
                format!(
                    "{{\"baud\":{baud},\"format\":\"{format}\",\"framing\":\"{}\"}}",
                    framing.name()
                ),
                units.join(","),
                t.requests() as f64 / h.listened.as_secs_f64().max(0.001),
                t.frames,
            )
        }
    };
    format!(
        "{{\"target\":{},\"listen\":true,\"setting\":{setting},\"units\":[{units}],\"frames\":{frames},\"requests_per_s\":{rate:.2},\"settings\":{},\"interrupted\":{},\"elapsed_s\":{:.3}}}",
        super::report::js(target),
        h.settings,
        h.interrupted,
        h.elapsed.as_secs_f64()
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What a wire carries: 9600 baud at 8N1 is 960 bytes a second; 3 s of it and a
    /// read's worth more. An hour at 115 200 baud 8E1: 37.7 MB.
    #[test]
    fn a_setting_is_listened_to_for_what_its_wire_carries() {
        let at = |baud, format: &str| ProbeSetting {
            baud,
            format: format.parse().unwrap(),
            framings: vec![SerialFraming::Rtu],
        };
        assert_eq!(
            most_bytes(&at(9600, "8N1"), Duration::from_secs(3)),
            2880 + 1024
        );
        assert_eq!(
            most_bytes(&at(115_200, "8E1"), Duration::from_secs(3600)),
            37_701_818 + 1024
        );
    }
}
