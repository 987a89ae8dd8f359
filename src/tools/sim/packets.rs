//! The simulator's packet log (docs/protocol.md §4: the slave "shows and clears a log of
//! request and response packets"). Bounded: the oldest entries go first.

use crate::frame::hex::Hex;
use std::collections::VecDeque;
use std::fmt;
use std::time::Instant;

/// Entries kept; older ones are forgotten.
pub(crate) const CAPACITY: usize = 1000;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum PacketDirection {
    /// A request the simulator received.
    Rx,
    /// A reply or notification it sent.
    Tx,
}

#[derive(Debug, Clone)]
pub(crate) struct PacketEntry {
    pub(crate) at: Instant,
    pub(crate) direction: PacketDirection,
    pub(crate) bytes: Vec<u8>,
    /// What happened to it: "reply", "ignored: busy", "notification", ...
    pub(crate) note: &'static str,
}

#[derive(Debug)]
pub(crate) struct PacketLog {
    start: Instant,
    entries: VecDeque<PacketEntry>,
    /// Entries ever recorded, including forgotten ones.
    pub(crate) total: u64,
}

impl Default for PacketLog {
    fn default() -> Self {
        Self {
            start: Instant::now(),
            entries: VecDeque::new(),
            total: 0,
        }
    }
}

impl PacketLog {
    pub(crate) fn record(&mut self, direction: PacketDirection, bytes: &[u8], note: &'static str) {
        if self.entries.len() == CAPACITY {
            self.entries.pop_front();
        }
        self.entries.push_back(PacketEntry {
            at: Instant::now(),
            direction,
            bytes: bytes.to_vec(),
            note,
        });
        self.total += 1;
    }

    pub(crate) fn clear(&mut self) {
        self.entries.clear();
    }

    pub(crate) fn len(&self) -> usize {
        self.entries.len()
    }

    #[cfg(test)]
    pub(crate) fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The last `n` entries (all when `None`), one a line.
    pub(crate) fn render(&self, n: Option<usize>) -> String {
        let skip = n.map_or(0, |n| self.entries.len().saturating_sub(n));
        let mut out = String::new();
        for e in self.entries.iter().skip(skip) {
            out.push_str(&format!("{}\n", LogLine(self.start, e)));
        }
        if out.is_empty() {
            out.push_str("(no packets)\n");
        }
        out
    }
}

/// One entry of the log as a line of text: its time since the log began, its way,
/// its bytes.
struct LogLine<'a>(Instant, &'a PacketEntry);

impl fmt::Display for LogLine<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let LogLine(start, e) = self;
        let t = e.at.saturating_duration_since(*start).as_secs_f64();
        let dir = match e.direction {
            PacketDirection::Rx => "rx",
            PacketDirection::Tx => "tx",
        };
        write!(f, "{t:10.3} {dir} {} ({})", Hex(&e.bytes), e.note)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bounded_and_rendered() {
        let mut log = PacketLog::default();
        assert_eq!(log.render(None), "(no packets)\n");
        for i in 0..(CAPACITY + 5) {
            log.record(PacketDirection::Rx, &[i as u8], "request");
        }
        assert_eq!((log.len(), log.total), (CAPACITY, CAPACITY as u64 + 5));
        let last = log.render(Some(2));
        let lines: Vec<&str> = last.lines().collect();
        assert_eq!(lines.len(), 2);
        assert!(lines[1].ends_with("rx EC (request)"), "{}", lines[1]);
        log.clear();
        assert!(log.is_empty());
    }
}
