//! The status page on the metrics listener: `/` is the page (`status.html`, plain HTML
//! and a little JavaScript from the binary, no external assets), `/status.json` what it
//! polls every second: each line's numbers, its units, its last frames decoded, and the
//! listeners. Asking for it turns the frame list on for a while ([`LineMetrics::watched`]):
//! the relay records frames only while someone looks.

use super::{Board, FrameSeen, LineMetrics};
use crate::frame::hex::Hex;
use std::fmt::Write as _;
use std::sync::atomic::AtomicU64;
use std::sync::Arc;
use std::time::SystemTime;
use tokio::time::Instant;

/// The page.
pub(crate) const HTML: &str = include_str!("status.html");

/// Points kept: a minute, one a second.
const KEPT: usize = 61;

/// A line's totals at one instant, sampled every second for the page's rates and chart.
#[derive(Debug, Clone, Copy)]
struct Point {
    at_ms: u128,
    requests: u64,
    reply_sum: f64,
    replies: u64,
    timeouts: u64,
}

/// A line's last minute.
#[derive(Debug, Default)]
pub(crate) struct History(std::collections::VecDeque<Point>);

/// Samples every line's totals once a second until `stop`, so the page shows the last
/// minute from its first load (reading the relay's atomics: the relay never waits).
pub(crate) async fn sample(board: Arc<Board>, stop: tokio_util::sync::CancellationToken) {
    loop {
        let at_ms = unix_ms();
        for l in board.lines() {
            let mut p = Point {
                at_ms,
                requests: l.stats.get(&l.stats.requests),
                reply_sum: 0.0,
                replies: 0,
                timeouts: 0,
            };
            for (_, u) in l.units() {
                let (sum, count, _) = u.histogram();
                p.reply_sum += sum;
                p.replies += count;
                p.timeouts += l.get(&u.timeouts);
            }
            let mut all = board.history.lock().expect("not poisoned");
            let h = all.entry(l.name.clone()).or_default();
            if h.0.len() == KEPT {
                h.0.pop_front();
            }
            h.0.push_back(p);
        }
        tokio::select! {
            _ = stop.cancelled() => return,
            _ = tokio::time::sleep(std::time::Duration::from_secs(1)) => {}
        }
    }
}

/// A line's last minute as JSON: for each second, its request rate, mean reply time
/// (null when no reply came) and timeouts.
fn history(board: &Board, name: &str) -> String {
    let all = board.history.lock().expect("not poisoned");
    let Some(h) = all.get(name) else {
        return "[]".into();
    };
    let points: Vec<String> =
        h.0.iter()
            .zip(h.0.iter().skip(1))
            .map(|(a, b)| {
                let secs = (b.at_ms.saturating_sub(a.at_ms)) as f64 / 1000.0;
                let rate = if secs > 0.0 {
                    (b.requests - a.requests) as f64 / secs
                } else {
                    0.0
                };
                let replies = b.replies - a.replies;
                let reply_ms =
                    (replies > 0).then(|| 1000.0 * (b.reply_sum - a.reply_sum) / replies as f64);
                format!(
                    "{{\"t\":{},\"rate\":{rate:.2},\"reply_ms\":{},\"timeouts\":{}}}",
                    b.at_ms,
                    opt(reply_ms.map(|v| format!("{v:.2}"))),
                    b.timeouts - a.timeouts
                )
            })
            .collect();
    format!("[{}]", points.join(","))
}

fn unix_ms() -> u128 {
    SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .unwrap_or_default()
        .as_millis()
}

/// `s` as a JSON string.
fn string(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 2);
    out.push('"');
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            c if (c as u32) < 0x20 => {
                let _ = write!(out, "\\u{:04x}", c as u32);
            }
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

fn opt(v: Option<impl std::fmt::Display>) -> String {
    v.map_or_else(|| "null".to_owned(), |v| v.to_string())
}

fn frame(f: &FrameSeen) -> String {
    let (addr, count) = f.span.unzip();
    format!(
        "{{\"t\":{},\"dir\":{},\"conn\":{},\"unit\":{},\"fc\":{},\"addr\":{},\"count\":{},\"hex\":{}}}",
        f.at_ms,
        string(f.dir),
        opt(f.conn),
        f.unit,
        f.function,
        opt(addr),
        opt(count),
        string(&Hex(&f.bytes).to_string())
    )
}

fn line(board: &Board, l: &LineMetrics, now: Instant) -> String {
    // The frames first: a first request shows none, then recording starts.
    let (frames, total) = l.frames();
    l.watched(now);
    let g = |a: &AtomicU64| l.get(a);
    let st = &l.stats;
    let units: Vec<String> = l
        .units()
        .map(|(unit, u)| {
            let (sum, count, _) = u.histogram();
            format!(
                "{{\"unit\":{unit},\"requests\":{},\"replies\":{},\"timeouts\":{},\"backed_off\":{},\"not_answering\":{},\"reply_sum_s\":{sum},\"reply_count\":{count}}}",
                g(&u.requests),
                g(&u.replies),
                g(&u.timeouts),
                g(&u.backed_off) == 1,
                l.not_answering(u, now),
            )
        })
        .collect();
    let timeouts: u64 = l.units().map(|(_, u)| g(&u.timeouts)).sum();
    let device: u64 = l.device_exceptions().iter().map(|(_, n)| n).sum();
    let gateway = st.get(&st.timeouts)
        + st.get(&st.backed_off)
        + st.get(&st.busy)
        + st.get(&st.unavailable)
        + st.get(&st.broadcasts_refused);
    let frames: Vec<String> = frames.iter().map(frame).collect();
    format!(
        "{{\"name\":{},\"open\":{},\"masters\":{},\"queued\":{},\"in_flight\":{},\"requests\":{},\"replies\":{},\"timeouts\":{timeouts},\"retries\":{},\"late\":{},\"exceptions_device\":{device},\"exceptions_gateway\":{gateway},\"busy_s\":{},\"last_reply_ms\":{},\"units\":[{}],\"frames_total\":{total},\"frames\":[{}],\"history\":{}}}",
        string(&l.name),
        g(&l.port_open) == 1,
        g(&l.masters),
        g(&l.queued),
        g(&l.in_flight),
        st.get(&st.requests),
        st.get(&st.replies),
        st.get(&st.retries),
        st.get(&st.late_replies),
        g(&l.busy_us) as f64 / 1e6,
        opt(l.since_last_reply(now).map(|d| d.as_millis())),
        units.join(","),
        frames.join(","),
        history(board, &l.name),
    )
}

/// What `/status.json` answers.
pub(crate) fn json(board: &Board) -> String {
    let now = Instant::now();
    let unix_ms = unix_ms();
    let lines: Vec<String> = board.lines().iter().map(|l| line(board, l, now)).collect();
    let listeners: Vec<String> = board
        .listeners()
        .iter()
        .map(|l| {
            let s = &l.stats;
            format!(
                "{{\"name\":{},\"masters\":{},\"connections\":{},\"refused\":{},\"violations\":{},\"denied_connections\":{},\"tls_failed\":{},\"tls_refused\":{},\"denied_requests\":{}}}",
                string(&l.name),
                l.connected(),
                s.get(&s.connections),
                s.get(&s.connections_refused),
                s.get(&s.protocol_violations),
                s.get(&s.connections_denied),
                s.get(&s.tls_failed),
                s.get(&s.tls_refused),
                s.get(&s.denied),
            )
        })
        .collect();
    let masters: Vec<String> = board
        .masters
        .list()
        .iter()
        .map(|m| {
            let (role, subject) = match &m.tls {
                Some((r, s)) => (string(r), string(s)),
                None => ("null".into(), "null".into()),
            };
            format!(
                "{{\"conn\":{},\"listener\":{},\"peer\":{},\"since_ms\":{},\"role\":{role},\"subject\":{subject}}}",
                m.conn,
                string(&m.listener),
                string(&m.peer.to_string()),
                (m.since * 1000.0) as u64,
            )
        })
        .collect();
    format!(
        "{{\"now_ms\":{unix_ms},\"lines\":[{}],\"listeners\":[{}],\"masters\":[{}]}}\n",
        lines.join(","),
        listeners.join(","),
        masters.join(",")
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stats::Stats;

    #[test]
    fn json_strings_are_escaped_and_frames_listed_only_while_watched() {
        assert_eq!(string("a\"b\\c\n"), "\"a\\\"b\\\\c\\u000a\"");
        let l = Arc::new(LineMetrics::new("/dev/\"x\"", Arc::new(Stats::default())));
        let seen = FrameSeen {
            at_ms: 5,
            dir: "gw->serial",
            conn: Some(3),
            unit: 1,
            function: 3,
            span: Some((10, 2)),
            bytes: vec![1, 0xAB],
        };
        assert!(!l.is_watched(Instant::now()));
        let board = Board::default();
        board.add_line(l.clone());
        let j = json(&board);
        assert!(j.contains("\"name\":\"/dev/\\\"x\\\"\""), "{j}");
        assert!(l.is_watched(Instant::now()), "asked: watched for a while");
        l.record(seen);
        let j = json(&board);
        assert!(
            j.contains("\"frames_total\":1,\"frames\":[{\"t\":5,\"dir\":\"gw->serial\",\"conn\":3,\"unit\":1,\"fc\":3,\"addr\":10,\"count\":2,\"hex\":\"01 AB\"}]"),
            "{j}"
        );
    }
}
