//! systemd's STATUS= line, refreshed every [`EVERY`] while the gateway runs under
//! systemd (`systemctl status` shows it): "2 masters, 14.2 req/s, last reply 12 ms ago,
//! 0 timeouts in the last minute", from the [`Board`]'s numbers.

use super::Board;
use crate::ops::notify;
use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

/// How often the line is refreshed.
pub(crate) const EVERY: Duration = Duration::from_secs(2);
const MINUTE: Duration = Duration::from_secs(60);

/// The numbers behind the line, kept between refreshes for the rates.
pub(crate) struct StatusLine {
    /// The requests counted at the last refresh, and when.
    requests: (Instant, u64),
    /// Timeouts counted at each refresh of the last minute, oldest first.
    timeouts: VecDeque<(Instant, u64)>,
}

/// Totals over every line and listener at one instant.
struct StatusTotals {
    masters: u64,
    requests: u64,
    timeouts: u64,
    last_reply: Option<Duration>,
    closed: Vec<String>,
}

fn totals(board: &Board, now: Instant) -> StatusTotals {
    let lines = board.lines();
    let get = |a: &std::sync::atomic::AtomicU64| a.load(std::sync::atomic::Ordering::Relaxed);
    StatusTotals {
        masters: board.listeners().iter().map(|l| l.connected()).sum(),
        requests: lines.iter().map(|l| get(&l.stats.requests)).sum(),
        timeouts: lines
            .iter()
            .flat_map(|l| l.units().map(|(_, u)| get(&u.timeouts)).collect::<Vec<_>>())
            .sum(),
        last_reply: lines.iter().filter_map(|l| l.since_last_reply(now)).min(),
        closed: lines
            .iter()
            .filter(|l| get(&l.port_open) == 0)
            .map(|l| l.name.clone())
            .collect(),
    }
}

impl StatusLine {
    /// Starts counting from the numbers `board` has at `now`.
    pub(crate) fn new(board: &Board, now: Instant) -> Self {
        let t = totals(board, now);
        Self {
            requests: (now, t.requests),
            timeouts: VecDeque::from([(now, t.timeouts)]),
        }
    }

    /// The line at `now`; the rate is over the time since the last call.
    pub(crate) fn line(&mut self, board: &Board, now: Instant) -> String {
        let t = totals(board, now);
        let (then, before) = self.requests;
        let secs = now.saturating_duration_since(then).as_secs_f64();
        let rate = if secs > 0.0 {
            t.requests.saturating_sub(before) as f64 / secs
        } else {
            0.0
        };
        self.requests = (now, t.requests);
        // The oldest count no older than a minute (or the first, in the first minute).
        while self.timeouts.len() > 1 && now - self.timeouts[1].0 >= MINUTE {
            self.timeouts.pop_front();
        }
        let minute_ago = self.timeouts.front().map_or(t.timeouts, |(_, n)| *n);
        self.timeouts.push_back((now, t.timeouts));
        let masters = match t.masters {
            1 => "1 master".to_owned(),
            n => format!("{n} masters"),
        };
        let last = match t.last_reply {
            None => "no reply yet".to_owned(),
            Some(ago) => format!("last reply {} ago", ago_text(ago)),
        };
        let timeouts = match t.timeouts.saturating_sub(minute_ago) {
            1 => "1 timeout".to_owned(),
            n => format!("{n} timeouts"),
        };
        let mut line = format!("{masters}, {rate:.1} req/s, {last}, {timeouts} in the last minute");
        for closed in t.closed {
            line += &format!("; {closed} not open");
        }
        line
    }
}

/// `12 ms`, `3.4 s`, `5 min`.
fn ago_text(d: Duration) -> String {
    if d < Duration::from_secs(1) {
        format!("{} ms", d.as_millis())
    } else if d < Duration::from_secs(120) {
        format!("{:.1} s", d.as_secs_f64())
    } else {
        format!("{} min", d.as_secs() / 60)
    }
}

/// Sends the line to systemd every [`EVERY`] until `stop`.
pub(crate) async fn refresh(board: Arc<Board>, stop: CancellationToken) {
    let mut status = StatusLine::new(&board, Instant::now());
    loop {
        tokio::select! {
            _ = stop.cancelled() => return,
            _ = tokio::time::sleep(EVERY) => {}
        }
        notify::status(&status.line(&board, Instant::now()));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ops::metrics::{LineMetrics, ListenerMetrics};
    use crate::ops::stats::Stats;
    use std::sync::atomic::Ordering;

    #[test]
    fn the_line_counts_rates_and_the_last_minute() {
        let stats = Arc::new(Stats::default());
        let line = Arc::new(LineMetrics::new("/dev/ttyX", stats.clone()));
        let board = Board::default();
        board.add_line(line.clone());
        board.add_listener(Arc::new(ListenerMetrics {
            name: "x".into(),
            stats: stats.clone(),
        }));
        let t0 = Instant::now();
        let mut s = StatusLine::new(&board, t0);
        line.port_open.store(1, Ordering::Relaxed);
        stats.add(&stats.connections, 2);
        stats.add(&stats.requests, 20);
        assert_eq!(
            s.line(&board, t0 + EVERY),
            "2 masters, 10.0 req/s, no reply yet, 0 timeouts in the last minute"
        );
        line.unit(1).requests.fetch_add(3, Ordering::Relaxed);
        line.unit(1).timeouts.fetch_add(3, Ordering::Relaxed);
        stats.add(&stats.connections_closed, 1);
        line.replied_at(t0 + Duration::from_secs(3));
        let t = t0 + Duration::from_secs(4);
        assert_eq!(
            s.line(&board, t),
            "1 master, 0.0 req/s, last reply 1.0 s ago, 3 timeouts in the last minute"
        );
        // A minute later the timeouts have aged out; a closed port is said.
        line.port_open.store(0, Ordering::Relaxed);
        let mut t = t;
        for _ in 0..31 {
            t += EVERY;
            s.line(&board, t);
        }
        let l = s.line(&board, t + EVERY);
        assert!(
            l.ends_with("0 timeouts in the last minute; /dev/ttyX not open"),
            "{l}"
        );
    }
}
