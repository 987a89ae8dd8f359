//! What the relay tells about its line as it goes (README "Watching it run"): the
//! numbers of `crate::ops::metrics` (requests, replies, reply times, timeouts, exceptions,
//! queue, time busy), one warning when a unit stops answering (or when its answers
//! were being dropped: too early, echoes, stale, naming the setting) and one line when
//! it answers again, the traffic log of whole frames (`log.traffic`), and the line's
//! packets for the capture and the status page's last frames (docs/capture.md),
//! through its tap while anyone looks.
//!
//! Plain data and a few relaxed atomic stores, the time passed in: the relay never
//! waits on whoever reads the numbers, and a capture's packets go out by `try_send`.

use crate::config::Framing;
use crate::frame::hex::Hex;
use crate::frame::Adu;
use crate::frame::FunctionCode as F;
use crate::ops::capture::dropped::Dropped;
use crate::ops::capture::packet::{Dir, Packet, Part, Proto, Reason};
use crate::ops::capture::Tap;
use crate::ops::metrics::LineMetrics;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;
use tokio::time::Instant;
use tracing::{debug, info, warn};

/// Timeouts in a row, with no reply between them, that make a unit "not answering".
/// On RTU/ASCII it is the default `unit_backoff_after`: the warning comes with the
/// back-off.
pub(super) const NOT_ANSWERING_AFTER: u32 = 3;
/// The least time between two warnings about one unit: a unit that comes and goes
/// does not fill the log. Spells in between are counted and said in the next warning.
pub(super) const WARN_EVERY: Duration = Duration::from_secs(60);

/// One unit's run of timeouts.
#[derive(Debug, Default, Clone)]
struct Spell {
    /// Timeouts since its last reply.
    timeouts: u32,
    /// When the first of them came.
    first: Option<Instant>,
    /// Whether this spell was warned about (then its end is said too).
    warned: bool,
    last_warning: Option<Instant>,
    /// Spells since the last warning that were not warned about (rate limit).
    unsaid: u32,
    /// The line's drop counters by reason when the unit's last request was sent.
    sent_drops: Option<Drops>,
    /// Bytes dropped by reason while its requests of this spell were on the line.
    dropped: Drops,
}

/// Bytes dropped, by reason: too early, echo, stale (`crate::ops::stats`).
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub(super) struct Drops {
    too_early: u64,
    echo: u64,
    stale: u64,
}

impl Drops {
    fn of(stats: &crate::ops::stats::Stats) -> Drops {
        Drops {
            too_early: stats.get(&stats.dropped_too_early),
            echo: stats.get(&stats.dropped_echo),
            stale: stats.get(&stats.dropped_stale),
        }
    }

    fn since(self, before: Drops) -> Drops {
        Drops {
            too_early: self.too_early - before.too_early,
            echo: self.echo - before.echo,
            stale: self.stale - before.stale,
        }
    }

    fn add(&mut self, more: Drops) {
        self.too_early += more.too_early;
        self.echo += more.echo;
        self.stale += more.stale;
    }

    /// What the warning says when bytes were dropped meanwhile: how many, why, and the
    /// setting that decides it; `None` when none were.
    pub(super) fn said(&self, baud: u32) -> Option<String> {
        let Drops {
            too_early,
            echo,
            stale,
        } = *self;
        if too_early >= echo.max(stale) && too_early > 0 {
            Some(format!(
                "its answers were dropped: {too_early} bytes came before the request could \
                 have left the wire at serial.baud_rate = {baud}. If nothing but a pty or a \
                 virtual port is between mbgate and the device, set serial.port_kind = \
                 \"pty\"; otherwise check serial.baud_rate against the device's"
            ))
        } else if echo >= stale && echo > 0 {
            Some(format!(
                "its answers were dropped as echoes: {echo} bytes were copies of the request \
                 that began before it could have left the wire at serial.baud_rate = {baud}. \
                 If nothing but a pty or a virtual port is between mbgate and the device, set \
                 serial.port_kind = \"pty\"; otherwise check serial.baud_rate against the \
                 device's"
            ))
        } else if stale > 0 {
            Some(format!(
                "{stale} bytes were dropped as stale (there before their request was sent: \
                 late answers?); relay.response_timeout_ms may be shorter than the device takes"
            ))
        } else {
            None
        }
    }
}

/// What the relay tells about its line: see the module notes.
pub(super) struct Telemetry {
    pub(super) metrics: Arc<LineMetrics>,
    /// `serial.baud_rate`, for the warnings.
    pub(super) baud: u32,
    spells: Vec<Spell>,
    /// When the line last had a request on it, while it has.
    busy_since: Option<Instant>,
    traffic: bool,
    /// The line's framing: how its frames are shown to Wireshark.
    framing: Framing,
    /// Where the line's packets go for the capture and the status page.
    pub(super) tap: Tap,
}

impl Telemetry {
    pub(super) fn new(
        metrics: Arc<LineMetrics>,
        traffic: bool,
        framing: Framing,
        baud: u32,
    ) -> Self {
        Self {
            metrics,
            baud,
            spells: vec![Spell::default(); 256],
            busy_since: None,
            traffic,
            framing,
            tap: Tap::off(),
        }
    }

    fn line(&self) -> &str {
        &self.metrics.name
    }

    /// A request for `unit` reached the relay.
    pub(super) fn request(&self, unit: u8) {
        self.metrics
            .unit(unit)
            .requests
            .fetch_add(1, Ordering::Relaxed);
    }

    /// The end of a turn of the loop: the gauges as they are now, and the time the
    /// line was busy (a request on it) since the last turn.
    pub(super) fn turn(&mut self, now: Instant, queued: usize, in_flight: usize, open: bool) {
        let m = &self.metrics;
        m.queued.store(queued as u64, Ordering::Relaxed);
        m.in_flight.store(in_flight as u64, Ordering::Relaxed);
        m.port_open.store(u64::from(open), Ordering::Relaxed);
        if let Some(since) = self.busy_since.take() {
            let us = now.saturating_duration_since(since).as_micros() as u64;
            m.busy_us.fetch_add(us, Ordering::Relaxed);
        }
        if in_flight > 0 {
            self.busy_since = Some(now);
        }
    }

    /// A request of priority class `class` waited `took` in the queue before its first
    /// sending.
    pub(super) fn waited(&self, class: u8, took: std::time::Duration) {
        let classes = &self.metrics.queue_wait;
        classes[usize::from(class).min(classes.len() - 1)].observe(took);
    }

    /// Masters attached to the line now.
    pub(super) fn masters(&self, n: usize) {
        self.metrics.masters.store(n as u64, Ordering::Relaxed);
    }

    /// Is anyone capturing the line's packets (a capture, the status page)?
    pub(super) fn capturing(&self) -> bool {
        self.tap.on()
    }

    /// Is anyone looking at the frames: the traffic log, a capture, the status page?
    pub(super) fn wants_frames(&self) -> bool {
        self.traffic || self.tap.on()
    }

    /// Request `adu` from master `conn` goes on the line as `tid`, as `bytes`.
    pub(super) fn sent(&mut self, conn: u64, adu: &Adu, tid: u16, bytes: &[u8], now: Instant) {
        self.spells[usize::from(adu.unit())].sent_drops = Some(Drops::of(&self.metrics.stats));
        if self.tap.on() {
            self.tap.send_with((Dir::Out, Part::Query), now, |p| {
                p.set_line_frame(self.framing, adu, bytes);
                p.conn = Some(conn);
                p.span = span(adu.pdu());
                p.label = "gw->serial";
            });
        }
        if self.traffic {
            let (addr, count) = span(adu.pdu()).unzip();
            debug!(
                target: "mbgate::traffic",
                dir = "gw->serial",
                conn,
                unit = adu.unit(),
                tid = adu.tid(),
                line_tid = tid,
                fc = adu.function(),
                addr,
                count,
                "{}",
                Hex(bytes)
            );
        }
    }

    pub(super) fn set_traffic(&mut self, on: bool) {
        self.traffic = on;
    }

    /// The reply `frame` (with the line's id) to `asked` from master `conn`, as it
    /// was on the wire (`wire`), taken off the line at `at`: for the capture.
    pub(super) fn taken(&self, conn: u64, asked: &Adu, frame: &Adu, wire: &[u8], at: Instant) {
        if self.tap.on() {
            self.tap.send_with((Dir::In, Part::Reply), at, |p| {
                p.set_line_frame(self.framing, frame, wire);
                p.conn = Some(conn);
                p.span = span(asked.pdu());
                p.label = "serial->gw";
            });
        }
    }

    /// Bytes the line dropped, for the capture.
    pub(super) fn dropped(&self, d: Dropped, now: Instant) {
        // What comes off a line of devices is a reply, but for the echo of a request.
        let role = if d.reason == Reason::Echo {
            Part::Query
        } else {
            Part::Reply
        };
        let p = Packet::dropped(Some(self.framing), d.reason, d.bytes, d.whole, d.detail);
        let p = p.shown_as(role);
        self.tap.send(p, d.at.unwrap_or(now));
    }

    /// The reply `frame` (with the line's id) answered `asked` from master `conn`,
    /// which left at `left`; `wire` is the reply as it was on the wire (given when the
    /// traffic log is on).
    pub(super) fn replied(
        &mut self,
        conn: u64,
        asked: &Adu,
        frame: &Adu,
        wire: Option<&[u8]>,
        (left, now): (Instant, Instant),
    ) {
        let unit = asked.unit();
        let u = self.metrics.unit(unit);
        u.replies.fetch_add(1, Ordering::Relaxed);
        u.observe(now.saturating_duration_since(left));
        u.backed_off.store(0, Ordering::Relaxed);
        u.not_answering.store(0, Ordering::Relaxed);
        self.metrics.replied_at(now);
        let exception = (frame.function() & 0x80 != 0).then(|| frame.pdu().get(1).copied());
        if let Some(code) = exception {
            self.metrics.device_exception(code.unwrap_or(0));
        }
        if let (Some(wire), true) = (wire, self.traffic) {
            let (addr, count) = span(asked.pdu()).unzip();
            debug!(
                target: "mbgate::traffic",
                dir = "serial->gw",
                conn,
                unit,
                tid = asked.tid(),
                line_tid = frame.tid(),
                fc = frame.function(),
                addr,
                count,
                exception = exception.flatten(),
                "{}",
                Hex(wire)
            );
        }
        let spell = std::mem::take(&mut self.spells[usize::from(unit)]);
        self.spells[usize::from(unit)] = Spell {
            last_warning: spell.last_warning,
            unsaid: spell.unsaid,
            sent_drops: spell.sent_drops,
            ..Spell::default()
        };
        if spell.warned {
            let over = spell.first.map_or(Duration::ZERO, |f| now - f);
            info!(
                unit,
                line = self.line(),
                "unit {unit} on {} answering again, after {} timeouts in {}",
                self.line(),
                spell.timeouts,
                secs(over)
            );
        }
    }

    /// A frame from the device that answers nothing on the line: `what` it is, and
    /// the frame as on the wire, taken off the line at `at`.
    pub(super) fn unsolicited(&self, what: &str, frame: &Adu, wire: &[u8], at: Instant) {
        if self.tap.on() {
            let p = if what.starts_with("late") {
                Packet::dropped(
                    Some(self.framing),
                    Reason::Stale,
                    wire.to_vec(),
                    true,
                    "a reply to a request already answered or timed out",
                )
                .shown_as(Part::Reply)
            } else {
                let mut p = Packet::line_frame(self.framing, frame, wire, Dir::In, Part::Reply);
                p.label = "unsolicited";
                let note = format!("a frame that answers no request: {what}");
                p.note = Some(match p.note {
                    Some(ascii) => format!("{note}; {ascii}"),
                    None => note,
                });
                p
            };
            self.tap.send(p, at);
        }
        if !self.traffic {
            return;
        }
        debug!(
            target: "mbgate::traffic",
            dir = "serial->gw",
            unit = frame.unit(),
            line_tid = frame.tid(),
            fc = frame.function(),
            "{} ({what})",
            Hex(wire)
        );
    }

    /// A request `asked` from master `conn` got no reply in time (one attempt).
    pub(super) fn timed_out(&mut self, conn: u64, asked: &Adu, now: Instant) {
        let unit = asked.unit();
        if self.tap.on() {
            let mut p = Packet::new(Dir::Neither, Part::Other, Proto::Data, Vec::new());
            p.conn = Some(conn);
            p.unit = Some(unit);
            p.function = Some(asked.function());
            p.span = span(asked.pdu());
            p.label = "timeout";
            p.note = Some(format!(
                "timeout: no reply from unit {unit} to function {} in time",
                asked.function()
            ));
            self.tap.send(p, now);
        }
        self.metrics.timed_out(unit, now);
        let line = self.metrics.name.clone();
        let drops = Drops::of(&self.metrics.stats);
        let baud = self.baud;
        let s = &mut self.spells[usize::from(unit)];
        if let Some(before) = s.sent_drops.replace(drops) {
            s.dropped.add(drops.since(before));
        }
        s.timeouts += 1;
        let first = *s.first.get_or_insert(now);
        if s.timeouts != NOT_ANSWERING_AFTER {
            return;
        }
        let u = self.metrics.unit(unit);
        u.not_answering.store(1, Ordering::Relaxed);
        if s.last_warning.is_some_and(|at| now - at < WARN_EVERY) {
            s.unsaid += 1;
            return;
        }
        let unsaid = match std::mem::take(&mut s.unsaid) {
            0 => String::new(),
            n => format!(
                " ({n} more such spells in the last {} not warned about)",
                secs(now - s.last_warning.unwrap_or(now))
            ),
        };
        s.warned = true;
        s.last_warning = Some(now);
        match s.dropped.said(baud) {
            Some(why) => warn!(
                unit,
                line = %line,
                "unit {unit} on {line}: {} timeouts in {}{unsaid}, and {why}",
                s.timeouts,
                secs(now - first)
            ),
            None => warn!(
                unit,
                line = %line,
                "unit {unit} on {line} not answering: {} timeouts in {}{unsaid}",
                s.timeouts,
                secs(now - first)
            ),
        }
    }

    /// `unit` was backed off (RTU/ASCII).
    pub(super) fn backed_off(&self, unit: u8) {
        let u = self.metrics.unit(unit);
        u.backed_off.store(1, Ordering::Relaxed);
    }
}

/// Seconds, to a tenth: `0.3 s`, `12.0 s`.
fn secs(d: Duration) -> String {
    format!("{:.1} s", d.as_secs_f64())
}

/// The first address and count a read or write request names (a single write: its
/// address and 1); `None` for the other functions.
pub(crate) fn span(pdu: &[u8]) -> Option<(u16, u16)> {
    let word = |i: usize| Some(u16::from_be_bytes([*pdu.get(i)?, *pdu.get(i + 1)?]));
    match F::new(*pdu.first()?) {
        F::READ_COILS
        | F::READ_DISCRETE_INPUTS
        | F::READ_HOLDING_REGISTERS
        | F::READ_INPUT_REGISTERS
        | F::WRITE_MULTIPLE_COILS
        | F::WRITE_MULTIPLE_REGISTERS
        | F::READ_WRITE_MULTIPLE_REGISTERS => Some((word(1)?, word(3)?)),
        F::WRITE_SINGLE_COIL | F::WRITE_SINGLE_REGISTER | F::MASK_WRITE_REGISTER => {
            Some((word(1)?, 1))
        }
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ops::stats::Stats;

    fn asked(unit: u8) -> Adu {
        Adu::build(1, unit, &[3, 0, 0, 0, 1])
    }

    fn telemetry() -> (Telemetry, Instant) {
        let m = Arc::new(LineMetrics::new("/dev/ttyX", Arc::new(Stats::default())));
        (
            Telemetry::new(m, false, Framing::Mbap, 19_200),
            Instant::now(),
        )
    }

    #[test]
    fn spans_of_reads_and_writes() {
        assert_eq!(span(&[3, 0, 10, 0, 4]), Some((10, 4)));
        assert_eq!(span(&[6, 1, 0, 0, 7]), Some((256, 1)));
        assert_eq!(span(&[0x10, 0, 1, 0, 2, 4, 0, 0, 0, 0]), Some((1, 2)));
        assert_eq!(span(&[0x17, 0, 5, 0, 3, 0, 9, 0, 1, 2, 0, 0]), Some((5, 3)));
        assert_eq!(span(&[8, 0, 0, 0, 0]), None);
        assert_eq!(span(&[3, 0]), None);
    }

    /// The health window: a unit not answering is failing while it keeps timing out,
    /// stops failing a minute after its last timeout when nobody asks it any more (a
    /// mistyped unit asked a few times), fails again at its next timeout, and is
    /// healthy again at once when it answers.
    #[test]
    fn a_unit_fails_while_it_times_out_and_until_it_answers_or_a_minute_passes() {
        let (mut w, t0) = telemetry();
        let at = |s: u64| t0 + Duration::from_secs(s);
        let failing = |w: &Telemetry, t| w.metrics.not_answering(w.metrics.unit(1), t);
        w.timed_out(7, &asked(1), at(0));
        w.timed_out(7, &asked(1), at(1));
        assert!(
            !failing(&w, at(1)),
            "two timeouts are not yet a unit not answering"
        );
        w.timed_out(7, &asked(1), at(2));
        assert!(failing(&w, at(2)));
        assert!(failing(
            &w,
            at(2) + crate::ops::metrics::HEALTH_WINDOW - Duration::from_millis(1)
        ));
        assert!(!failing(&w, at(2) + crate::ops::metrics::HEALTH_WINDOW));
        w.timed_out(7, &asked(1), at(100));
        assert!(failing(&w, at(100)), "asked again, and again no answer");
        w.replied(7, &asked(1), &asked(1), None, (at(101), at(101)));
        assert!(!failing(&w, at(101)), "it answered");
    }

    #[test]
    fn a_spell_is_warned_at_its_third_timeout_and_its_end_said() {
        let (mut w, t0) = telemetry();
        let s = |w: &Telemetry| w.spells[1].clone();
        w.timed_out(7, &asked(1), t0);
        w.timed_out(7, &asked(1), t0 + Duration::from_secs(1));
        assert!(!s(&w).warned);
        w.timed_out(7, &asked(1), t0 + Duration::from_secs(2));
        assert!(s(&w).warned);
        assert_eq!(w.metrics.unit(1).not_answering.load(Ordering::Relaxed), 1);
        assert_eq!(s(&w).last_warning, Some(t0 + Duration::from_secs(2)));
        w.timed_out(7, &asked(1), t0 + Duration::from_secs(3));
        assert_eq!(s(&w).last_warning, Some(t0 + Duration::from_secs(2)));
        assert_eq!(w.metrics.unit(1).timeouts.load(Ordering::Relaxed), 4);
        // Other units are not touched.
        assert_eq!(w.spells[2].timeouts, 0);
    }

    #[test]
    fn a_second_spell_within_the_minute_is_not_warned_but_counted() {
        let (mut w, t0) = telemetry();
        let req = Adu::build(1, 1, &[3, 0, 0, 0, 1]);
        let rep = Adu::build(1, 1, &[3, 2, 0, 0]);
        for i in 0..3 {
            w.timed_out(7, &asked(1), t0 + Duration::from_secs(i));
        }
        w.replied(1, &req, &rep, None, (t0, t0 + Duration::from_secs(5)));
        assert_eq!(w.spells[1].timeouts, 0);
        for i in 10..13 {
            w.timed_out(7, &asked(1), t0 + Duration::from_secs(i));
        }
        assert!(!w.spells[1].warned, "within a minute of the last warning");
        assert_eq!(w.spells[1].unsaid, 1);
        w.replied(1, &req, &rep, None, (t0, t0 + Duration::from_secs(20)));
        for i in 70..73 {
            w.timed_out(7, &asked(1), t0 + Duration::from_secs(i));
        }
        assert!(w.spells[1].warned, "a minute later");
        assert_eq!(w.spells[1].unsaid, 0);
    }
}
