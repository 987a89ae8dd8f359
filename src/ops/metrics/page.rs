//! The status page on the metrics listener: `/` is the page (`status.html`, plain HTML
//! and a little JavaScript from the binary, no external assets), `/status.json` what it
//! polls every second: each line's numbers, its units, its last frames decoded, and the
//! listeners. The last frames are the capture's packets of the line
//! (`crate::ops::capture`): asking for the page turns them on for a while
//! (`Hub::page`), so the relay makes packets only while someone looks.

use super::{Board, LineMetrics};
use crate::frame::hex::Hex;
use crate::ops::capture::hub::Recent;
use crate::ops::capture::packet::Packet;
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

/// A packet of the line as the page lists it: its time (milliseconds, and
/// microseconds), what it is, the master it belongs to, unit, function, address and
/// count, its bytes (for an ASCII frame, its unit, PDU and CRC; the text is in the
/// note), and the note (why bytes were dropped).
fn frame(board: &Board, f: &Packet) -> String {
    let (addr, count) = f.span.unzip();
    let master = f
        .conn
        .and_then(|c| board.capture.get()?.master(c))
        .map(|a| string(&a.to_string()));
    format!(
        "{{\"t\":{},\"us\":{},\"dir\":{},\"conn\":{},\"master\":{},\"unit\":{},\"fc\":{},\"addr\":{},\"count\":{},\"hex\":{},\"note\":{}}}",
        f.at_us / 1000,
        f.at_us,
        string(f.label),
        opt(f.conn),
        opt(master),
        opt(f.unit),
        opt(f.function),
        opt(addr),
        opt(count),
        string(&Hex(&f.bytes).to_string()),
        opt(f.note.as_deref().map(string)),
    )
}

fn line(board: &Board, l: &LineMetrics, recent: Option<&Recent>, now: Instant) -> String {
    let (frames, total) = recent.map_or((Vec::new(), 0), |r| (r.kept.iter().collect(), r.total));
    let g = |a: &AtomicU64| l.get(a);
    let st = &l.stats;
    let units: Vec<String> = l
        .units()
        .map(|(unit, u)| {
            let (sum, count, _) = u.histogram();
            // The bucket bound of the 99th percentile (infinity is no JSON number).
            let p99 = u.quantile_bound(0.99).filter(|b| b.is_finite());
            let (learned, why) = match u.learned() {
                Some((t, why)) => (Some(t.as_secs_f64()), Some(string(why))),
                None => (None, None),
            };
            format!(
                "{{\"unit\":{unit},\"requests\":{},\"replies\":{},\"timeouts\":{},\"backed_off\":{},\"not_answering\":{},\"reply_sum_s\":{sum},\"reply_count\":{count},\"reply_p99_le_s\":{},\"learned_timeout_s\":{},\"learned_why\":{}}}",
                g(&u.requests),
                g(&u.replies),
                g(&u.timeouts),
                g(&u.backed_off) == 1,
                l.not_answering(u, now),
                opt(p99),
                opt(learned),
                opt(why),
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
    let frames: Vec<String> = frames.iter().map(|f| frame(board, f)).collect();
    format!(
        "{{\"name\":{},\"direction\":{},\"open\":{},\"masters\":{},\"queued\":{},\"in_flight\":{},\"requests\":{},\"replies\":{},\"timeouts\":{timeouts},\"retries\":{},\"late\":{},\"exceptions_device\":{device},\"exceptions_gateway\":{gateway},\"busy_s\":{},\"last_reply_ms\":{},\"units\":[{}],\"frames_total\":{total},\"frames\":[{}],\"history\":{}}}",
        string(&l.name),
        l.direction().map_or_else(|| "null".to_owned(), |d| string(&d)),
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
    // The frames as kept so far: a first request shows none, then keeping starts.
    let recent = board.capture.get().map(|c| c.page()).unwrap_or_default();
    let lines: Vec<String> = board
        .lines()
        .iter()
        .enumerate()
        .map(|(i, l)| line(board, l, recent.get(i + 1), now))
        .collect();
    let listeners: Vec<String> = board
        .listeners_on()
        .iter()
        .map(|(l, transport)| {
            let s = &l.stats;
            format!(
                "{{\"name\":{},\"transport\":\"{}\",\"masters\":{},\"connections\":{},\"refused\":{},\"violations\":{},\"denied_connections\":{},\"tls_failed\":{},\"tls_refused\":{},\"denied_requests\":{}}}",
                string(&l.name),
                transport.label(),
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
    let capture_dropped = board.capture.get().map_or(0, |c| c.dropped());
    format!(
        "{{\"now_ms\":{unix_ms},\"lines\":[{}],\"listeners\":[{}],\"masters\":[{}],\"capture_dropped\":{capture_dropped}}}\n",
        lines.join(","),
        listeners.join(","),
        masters.join(",")
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ops::stats::Stats;

    #[tokio::test]
    async fn json_strings_are_escaped_and_frames_listed_only_while_watched() {
        use crate::ops::capture::packet::{Dir, Part, Proto};
        use crate::ops::capture::{Hub, Interface};
        assert_eq!(string("a\"b\\c\n"), "\"a\\\"b\\\\c\\u000a\"");
        let l = Arc::new(LineMetrics::new("/dev/\"x\"", Arc::new(Stats::default())));
        let iface = |n: &str| Interface {
            name: n.into(),
            description: String::new(),
        };
        let (hub, task) = Hub::new(vec![iface("tcp"), iface("/dev/\"x\"")]);
        tokio::spawn(task);
        let board = Board::default();
        board.add_line(l.clone());
        board.capture.set(hub.clone()).unwrap();
        let tap = hub.tap(1);
        assert!(!tap.on());
        let j = json(&board);
        assert!(
            j.contains("\"name\":\"/dev/\\\"x\\\"\",\"direction\":null,"),
            "{j}"
        );
        l.set_direction(Some("the gateway switches the transmitter by RTS".into()));
        let j = json(&board);
        assert!(
            j.contains("\"direction\":\"the gateway switches the transmitter by RTS\","),
            "the method of the line: {j}"
        );
        assert!(j.contains("\"frames_total\":0,\"frames\":[]"), "{j}");
        assert!(tap.on(), "asked: watched for a while");
        let mut p = Packet::new(Dir::Out, Part::Query, Proto::Mbtcp, vec![1, 0xAB]);
        (p.conn, p.unit, p.function, p.span) = (Some(3), Some(1), Some(3), Some((10, 2)));
        p.label = "gw->serial";
        tap.send(p, tokio::time::Instant::now());
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        let j = json(&board);
        assert!(
            j.contains("\"dir\":\"gw->serial\",\"conn\":3,\"master\":null,\"unit\":1,\"fc\":3,\"addr\":10,\"count\":2,\"hex\":\"01 AB\",\"note\":null}]"),
            "{j}"
        );
        assert!(j.contains("\"frames_total\":1,"), "{j}");
    }
}
