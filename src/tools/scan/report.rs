//! `mbgate scan`'s report (docs/scan.md): a table with a ready `[[line]]` block, or
//! one JSON object.

use super::probe::{self, SerialFraming};
use super::{Found, Report, ScanOptions};
use crate::tools::wire::uart::{Format, Parity};
use std::fmt::Write as _;
use std::time::Duration;

pub(super) fn parity_name(p: Parity) -> &'static str {
    match p {
        Parity::None => "none",
        Parity::Even => "even",
        Parity::Odd => "odd",
    }
}

fn identity(f: &Found) -> String {
    let mut parts = Vec::new();
    if let Ok(objects) = &f.device_id {
        let text: Vec<&str> = objects.iter().map(|(_, v)| v.as_str()).collect();
        if !text.is_empty() {
            parts.push(text.join(" "));
        }
    }
    if let Ok(data) = &f.server_id {
        parts.push(format!("server id {}", probe::server_id_text(data)));
    }
    if parts.is_empty() {
        "-".into()
    } else {
        parts.join("; ")
    }
}

/// The report as a table and a `[[line]]` block; or "nothing found" and a hint.
pub(crate) fn table(report: &Report, target: &str, tcp: bool, args: &ScanOptions) -> String {
    let took = format!(
        "{:.1} s, {} tries{}",
        report.elapsed.as_secs_f64(),
        report.tries,
        if report.interrupted {
            ", interrupted"
        } else {
            ""
        }
    );
    let _ = args;
    if report.found.is_empty() {
        return nothing_found(report, target, tcp, &took);
    }
    let mut s = found_table(report, target, &took);
    let _ = writeln!(s, "\nFor mbgate.toml:\n");
    line_blocks(report, target, &mut s);
    s
}

/// "nothing found", what came back instead, and a hint at what to try.
fn nothing_found(report: &Report, target: &str, tcp: bool, took: &str) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "nothing found on {target} ({took})");
    for (b, f, fr) in &report.garbage {
        let _ = writeln!(
            s,
            "bytes came back at {b} {f} {} but no frame with a good check",
            fr.name()
        );
    }
    for ((b, f, fr), (unit, function)) in &report.unanswering {
        let _ = writeln!(
            s,
            "frames with a good check came back at {b} {f} {} but answered no request \
             (the first: unit {unit}, FC {function:02})",
            fr.name()
        );
    }
    if let Some(closed) = &report.closed {
        let _ = writeln!(s, "{closed}");
    }
    let hint = if report.closed.is_some() {
        "hint: the peer accepts connections and closes them at once: is it a \
         Modbus/TCP server, does it allow this address (an allow list, a connection \
         limit already reached)?"
    } else if !report.unanswering.is_empty() {
        "hint: a device is there at that setting but answers a read of register 0 \
         with another function's frame (a device that answers every request alike, \
         or another master talking on the bus): give that setting with --baud, \
         --format and --framing and --units to look further"
    } else if tcp {
        "hint: is it a Modbus/TCP device (port 502)? Try more --units, a longer --timeout-ms"
    } else if report.garbage.is_empty() {
        "hint: nothing at all came back: check the wiring (RS-485 A and B swapped? \
         the bus terminated?), the device's power, and that it is a Modbus device; \
         every unit id was tried at 19200 and 9600 baud, 8E1 and 8N1, but only the \
         first --give-up ids elsewhere: give the setting you suspect with --baud, \
         --format, --framing and --give-up 247"
    } else {
        "hint: bytes came back without a good frame: a device is there at another \
         setting (try --all, or other --baud and --format), or the line is noisy"
    };
    let _ = writeln!(s, "{hint}");
    s
}

/// One row a unit found: its setting, what it answered, its reply times, its identity.
fn found_table(report: &Report, target: &str, took: &str) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "found on {target} ({took}):");
    let _ = writeln!(
        s,
        "{:<5} {:<7} {:<6} {:<8} {:<24} {:<14} identity",
        "unit", "baud", "format", "framing", "answered", "reply p50/max"
    );
    for f in &report.found {
        let (b, fmt, fr) = match f.serial {
            Some((b, fmt, fr)) => (b.to_string(), fmt.to_string(), fr.name()),
            None => ("-".into(), "-".into(), "mbap"),
        };
        let replies = match f.reply_time() {
            Some((p50, max)) => format!("{}/{} ms", ms(p50), ms(max)),
            None => "-".into(),
        };
        let _ = writeln!(
            s,
            "{:<5} {:<7} {:<6} {:<8} {:<24} {:<14} {}",
            f.unit,
            b,
            fmt,
            fr,
            f.answered,
            replies,
            identity(f)
        );
    }
    s
}

/// A `[[line]]` block for each setting found, with a `[[line.unit]]` for each slow
/// unit on it.
fn line_blocks(report: &Report, target: &str, s: &mut String) {
    let mut settings: Vec<Option<(u32, Format, SerialFraming)>> = Vec::new();
    for f in &report.found {
        if !settings.contains(&f.serial) {
            settings.push(f.serial);
        }
    }
    for setting in settings {
        let units: Vec<String> = report
            .found
            .iter()
            .filter(|f| f.serial == setting)
            .map(|f| f.unit.to_string())
            .collect();
        let _ = writeln!(s, "[[line]]\nunits = [{}]", units.join(", "));
        match setting {
            None => {
                let _ = writeln!(
                    s,
                    "tcp = {{ address = \"{target}\", framing = \"mbap\" }}\n"
                );
            }
            Some((b, f, fr)) => {
                let _ = writeln!(
                    s,
                    "serial = {{ path = \"{target}\", baud_rate = {b}, data_bits = {}, \
                     parity = \"{}\", stop_bits = {}, framing = \"{}\", flow_control = \"none\" }}\n",
                    f.data_bits,
                    parity_name(f.parity),
                    f.stop_bits,
                    fr.name()
                );
            }
        }
        let here: Vec<&Found> = report
            .found
            .iter()
            .filter(|f| f.serial == setting)
            .collect();
        for (f, timeout, why) in slow_units(&here) {
            let (p50, max) = f.reply_time().unwrap_or_default();
            let _ = writeln!(
                s,
                "[[line.unit]]    # replies in {} ms, at most {} ms: {why}\n\
                 units = [{}]\nresponse_timeout_ms = {timeout}\n",
                ms(p50),
                ms(max),
                f.unit
            );
        }
    }
}

/// Milliseconds, whole.
fn ms(d: Duration) -> u128 {
    d.as_millis()
}

/// The units of one line much slower than the rest, each with a
/// `response_timeout_ms` for it: twice its longest reply, rounded up to 10 ms, at
/// least 50. Slower is a longest reply over 3 times the line's typical reply (the
/// median of its units' medians) and over 50 ms, or one the line's default timeout
/// would cut short; so a lone device is named only in the second case.
pub(super) fn slow_units<'a>(found: &[&'a Found]) -> Vec<(&'a Found, u64, &'static str)> {
    let mut medians: Vec<Duration> = found
        .iter()
        .filter_map(|f| Some(f.reply_time()?.0))
        .collect();
    medians.sort();
    let Some(&typical) = medians.get(medians.len() / 2) else {
        return Vec::new();
    };
    let line_default =
        Duration::from_millis(crate::config::RelayConfig::default().response_timeout_ms);
    found
        .iter()
        .filter_map(|&f| {
            let (_, max) = f.reply_time()?;
            let slower = found.len() > 1 && max > typical * 3 && max > Duration::from_millis(50);
            let timeout = ((max.as_millis() as u64 * 2).div_ceil(10) * 10).max(50);
            let why = if slower {
                "slower than the rest"
            } else {
                "the default response_timeout_ms would cut it short"
            };
            (slower || max * 2 > line_default).then_some((f, timeout, why))
        })
        .collect()
}

/// A string as JSON.
pub(super) fn js(s: &str) -> String {
    let mut out = String::from("\"");
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            c if (c as u32) < 0x20 => out.push_str(&format!("\\u{:04x}", c as u32)),
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

/// One unit found, as a JSON object.
fn found_json(f: &Found) -> String {
    let setting = match f.serial {
        Some((b, fmt, fr)) => format!(
            "\"baud\":{b},\"format\":{},\"framing\":{}",
            js(&fmt.to_string()),
            js(fr.name())
        ),
        None => "\"framing\":\"mbap\"".into(),
    };
    let device_id = match &f.device_id {
        Ok(objects) => {
            let o: Vec<String> = objects
                .iter()
                .map(|(id, v)| format!("{}:{}", js(&id.to_string()), js(v)))
                .collect();
            format!("{{{}}}", o.join(","))
        }
        Err(_) => "null".into(),
    };
    let server_id = match &f.server_id {
        Ok(d) => js(&d.iter().map(|b| format!("{b:02X}")).collect::<String>()),
        Err(_) => "null".into(),
    };
    let replies = match f.reply_time() {
        Some((p50, max)) => format!(
            "\"reply_ms_p50\":{},\"reply_ms_max\":{},\"replies\":{}",
            ms(p50),
            ms(max),
            f.replies.len()
        ),
        None => "\"reply_ms_p50\":null,\"reply_ms_max\":null,\"replies\":0".into(),
    };
    format!(
        "{{\"unit\":{},{setting},\"answered\":{},\"device_id\":{device_id},\"server_id\":{server_id},{replies},\"found_s\":{:.1}}}",
        f.unit,
        js(&f.answered),
        f.after.as_secs_f64()
    )
}

/// The report as one JSON object.
pub(crate) fn json(report: &Report, target: &str, tcp: bool) -> String {
    let found: Vec<String> = report.found.iter().map(found_json).collect();
    let garbage: Vec<String> = report
        .garbage
        .iter()
        .map(|(b, f, fr)| {
            format!(
                "{{\"baud\":{b},\"format\":{},\"framing\":{}}}",
                js(&f.to_string()),
                js(fr.name())
            )
        })
        .collect();
    let unanswering: Vec<String> = report
        .unanswering
        .iter()
        .map(|((b, f, fr), (unit, function))| {
            format!(
                "{{\"baud\":{b},\"format\":{},\"framing\":{},\"unit\":{unit},\"function\":{function}}}",
                js(&f.to_string()),
                js(fr.name())
            )
        })
        .collect();
    let closed = report.closed.as_deref().map_or("null".into(), js);
    format!(
        "{{\"target\":{},\"tcp\":{tcp},\"found\":[{}],\"garbage\":[{}],\"unanswering\":[{}],\"closed\":{closed},\"interrupted\":{},\"elapsed_s\":{:.3},\"tries\":{}}}",
        js(target),
        found.join(","),
        garbage.join(","),
        unanswering.join(","),
        report.interrupted,
        report.elapsed.as_secs_f64(),
        report.tries
    )
}
