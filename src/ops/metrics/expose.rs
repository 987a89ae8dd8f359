//! The Prometheus exposition of the [`Board`]: read at scrape time from the relay's
//! atomics and encoded by `prometheus-client` in the OpenMetrics text format, which
//! Prometheus scrapes as is. Names follow Prometheus' conventions: `mbgate_` and the
//! thing counted, `_total` on counters, base units (`_seconds`, `_bytes`).
//!
//! Labels: `line` (the serial port's path, or host:port of a device server) on every
//! line's and unit's metric, `unit` on a unit's, `listener` (its address, or `dial
//! HOST:PORT`) and `transport` (`tcp`, `udp`) on a listener's, so a TCP and a UDP
//! listener on one address are two series, never one printed twice; exceptions also by `source` (`device`: the device sent it; `gateway`:
//! mbgate answered it itself) and `code` (`0x0B`).

use super::{Board, LineMetrics, ListenerMetrics, ListenerTransport};
use crate::frame::ExceptionCode;
use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeMetric};
use prometheus_client::metrics::counter::ConstCounter;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::metrics::MetricType;
use prometheus_client::registry::{Registry, Unit};
use std::sync::Arc;
use std::time::SystemTime;
use tokio::time::Instant;

/// The text a scrape of `/metrics` gets.
pub(crate) fn render(board: &Arc<Board>) -> String {
    let mut registry = Registry::default();
    registry.register_collector(Box::new(Scrape(board.clone())));
    let mut out = String::new();
    prometheus_client::encoding::text::encode(&mut out, &registry)
        .expect("writing to a String does not fail");
    out
}

/// The media type of [`render`]'s text.
pub(crate) const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

#[derive(Debug)]
struct Scrape(Arc<Board>);

type Labels = Vec<(&'static str, String)>;

/// One metric family: its name, help, unit and type, and a value per label set.
struct Family {
    name: &'static str,
    help: &'static str,
    unit: Option<Unit>,
    kind: MetricType,
    values: Vec<(Labels, f64)>,
}

impl Family {
    fn new(name: &'static str, help: &'static str, kind: MetricType) -> Self {
        Self {
            name,
            help,
            unit: None,
            kind,
            values: Vec::new(),
        }
    }

    fn seconds(mut self) -> Self {
        self.unit = Some(Unit::Seconds);
        self
    }

    fn encode(&self, e: &mut DescriptorEncoder) -> std::fmt::Result {
        let mut m = e.encode_descriptor(self.name, self.help, self.unit.as_ref(), self.kind)?;
        if let [(labels, v)] = &self.values[..] {
            if labels.is_empty() {
                // The gateway's own: `name value`, not `name{} value`.
                return self.value(*v, m);
            }
        }
        for (labels, v) in &self.values {
            self.value(*v, m.encode_family(labels)?)?;
        }
        Ok(())
    }

    fn value(&self, v: f64, m: prometheus_client::encoding::MetricEncoder) -> std::fmt::Result {
        match self.kind {
            MetricType::Counter if v.fract() == 0.0 => ConstCounter::new(v as u64).encode(m),
            MetricType::Counter => ConstCounter::new(v).encode(m),
            _ => ConstGauge::new(v).encode(m),
        }
    }
}

fn line_label(l: &LineMetrics) -> Labels {
    vec![("line", l.name.clone())]
}

/// `0x0B`, as exception codes are written in the Modbus specification.
fn code(c: u8) -> String {
    format!("0x{c:02X}")
}

impl Collector for Scrape {
    fn encode(&self, mut e: DescriptorEncoder) -> std::fmt::Result {
        let lines = self.0.lines();
        let listeners = self.0.listeners_on();
        let now = Instant::now();
        for f in line_families(&lines, now) {
            f.encode(&mut e)?;
        }
        unit_families(&lines, now, &mut e)?;
        for f in listener_families(&listeners) {
            f.encode(&mut e)?;
        }
        masters(&self.0.masters.list()).encode(&mut e)?;
        queue_wait(&lines, &mut e)?;
        for f in gateway_families(&self.0) {
            f.encode(&mut e)?;
        }
        Ok(())
    }
}

/// How long requests waited for the line, by line and priority class (`class`, 0 to
/// 7, docs/masters.md "Priority"), for the classes that have had a request: the
/// alert on a saturated line watches its 99th percentile.
fn queue_wait(lines: &[Arc<LineMetrics>], e: &mut DescriptorEncoder) -> std::fmt::Result {
    let mut m = e.encode_descriptor(
        "mbgate_line_queue_wait",
        "Time a request waited in the line's queue, from the relay taking it to its first sending, by the priority class it went as.",
        Some(&Unit::Seconds),
        MetricType::Histogram,
    )?;
    for l in lines {
        for (class, h) in l.queue_wait.iter().enumerate() {
            if h.count() == 0 {
                continue;
            }
            let labels = vec![("line", l.name.clone()), ("class", class.to_string())];
            let (sum, count, buckets) = h.get();
            let mut fam = m.encode_family(&labels)?;
            fam.encode_histogram::<Labels>(sum, count, &buckets, None)?;
        }
    }
    Ok(())
}

/// The gateway's own: its reloads (docs/configuration.md "Reload") and the packets
/// its captures lost (docs/capture.md).
fn gateway_families(board: &Board) -> Vec<Family> {
    use std::sync::atomic::Ordering::Relaxed;
    let r = &board.reloads;
    let one = |name, help, kind, v: f64| {
        let mut f = Family::new(name, help, kind);
        f.values.push((Vec::new(), v));
        f
    };
    let mut reloads = Family::new(
        "mbgate_config_reloads",
        "Reloads of the configuration, by result: taken (applied, or nothing to apply) or refused (the running configuration stays).",
        C,
    );
    for (result, n) in [("taken", &r.taken), ("refused", &r.refused)] {
        reloads
            .values
            .push((vec![("result", result.into())], n.load(Relaxed) as f64));
    }
    let dropped = board.capture.get().map_or(0, |h| h.dropped());
    vec![
        reloads,
        one(
            "mbgate_config_last_reload_successful",
            "0 while the last reload refused the file, else 1 (no reload yet: 1).",
            G,
            f64::from(u8::from(r.last_refused.load(Relaxed) == 0)),
        ),
        one(
            "mbgate_config_last_reload_success_timestamp",
            "When the configuration file was last taken, at start or by a reload (Unix time).",
            G,
            r.last_taken_us.load(Relaxed) as f64 / 1e6,
        )
        .seconds(),
        one(
            "mbgate_capture_dropped_packets",
            "Packets the captures (mbgate capture, and the always-on ring) lost because they fell behind: their records have holes.",
            C,
            dropped as f64,
        ),
    ]
}

/// A counter or gauge per line, read by `get`.
fn per_line(
    lines: &[Arc<LineMetrics>],
    (name, help, kind): (&'static str, &'static str, MetricType),
    get: impl Fn(&LineMetrics) -> f64,
) -> Family {
    let mut f = Family::new(name, help, kind);
    f.values = lines.iter().map(|l| (line_label(l), get(l))).collect();
    f
}

const C: MetricType = MetricType::Counter;
const G: MetricType = MetricType::Gauge;

fn line_families(lines: &[Arc<LineMetrics>], now: Instant) -> Vec<Family> {
    let s = |get: fn(&crate::ops::stats::Stats) -> &std::sync::atomic::AtomicU64| {
        move |l: &LineMetrics| l.stats.get(get(&l.stats)) as f64
    };
    let sum_units = |get: fn(&super::UnitMetrics) -> &std::sync::atomic::AtomicU64| {
        move |l: &LineMetrics| l.units().map(|(_, u)| l.get(get(u))).sum::<u64>() as f64
    };
    let mut families = vec![
        per_line(lines, ("mbgate_line_requests", "Requests from masters the line's relay took.", C), s(|s| &s.requests)),
        per_line(lines, ("mbgate_line_replies", "Device replies delivered to masters (device exceptions included).", C), s(|s| &s.replies)),
        per_line(lines, ("mbgate_line_timeouts", "Attempts the device did not answer in time (each resend counts).", C), sum_units(|u| &u.timeouts)),
        per_line(lines, ("mbgate_line_retries", "Requests resent after a timeout.", C), s(|s| &s.retries)),
        per_line(lines, ("mbgate_line_backed_off_requests", "Requests answered 0x0B at once, without the line: their unit was backed off (RTU/ASCII).", C), s(|s| &s.backed_off)),
        per_line(lines, ("mbgate_line_late_replies", "Replies to a request no longer on the line (timed out, or a duplicate of one answered): dropped.", C), s(|s| &s.late_replies)),
        per_line(lines, ("mbgate_line_bad_frames", "Replies that failed their CRC or LRC, or did not fit their request.", C), s(|s| &s.bad_frames)),
        per_line(lines, ("mbgate_line_refuted_frames", "MBAP replies that what followed showed to have lost bytes: dropped.", C), s(|s| &s.refuted_frames)),
        per_line(lines, ("mbgate_line_dropped_bytes", "Bytes from the device the decoder discarded (by reason: mbgate_line_dropped_bytes_by_reason).", C), s(|s| &s.dropped_bytes)),
        per_line(lines, ("mbgate_line_unasked_bytes", "MBAP: bytes from the device while nothing was asked and no late reply could come.", C), s(|s| &s.unasked_bytes)),
        per_line(lines, ("mbgate_line_notifications_dropped", "Frames answering no request, dropped.", C), s(|s| &s.notifications_dropped)),
        per_line(lines, ("mbgate_line_notifications_broadcast", "Frames answering no request, sent to every master.", C), s(|s| &s.notifications_broadcast)),
        per_line(lines, ("mbgate_line_withdrawn_bytes", "RTU/ASCII: bytes of requests that timed out before leaving the port, withdrawn from its output queue.", C), s(|s| &s.withdrawn_bytes)),
        per_line(lines, ("mbgate_line_opens", "Times the port was opened (the first open, then each reopen or reconnect).", C), s(|s| &s.serial_opens)),
        per_line(lines, ("mbgate_line_received_bytes", "Bytes read from the port.", C), s(|s| &s.serial_bytes_in)),
        per_line(lines, ("mbgate_line_sent_bytes", "Bytes written to the port.", C), s(|s| &s.serial_bytes_out)),
        per_line(lines, ("mbgate_line_busy", "Time with at least one request on the line.", C), |l| l.get(&l.busy_us) as f64 / 1e6).seconds(),
        per_line(lines, ("mbgate_line_queued", "Requests waiting for the line.", G), |l| l.get(&l.queued) as f64),
        per_line(lines, ("mbgate_line_in_flight", "Requests on the line, awaiting their reply.", G), |l| l.get(&l.in_flight) as f64),
        per_line(lines, ("mbgate_line_masters", "Masters attached to the line.", G), |l| l.get(&l.masters) as f64),
        per_line(lines, ("mbgate_line_port_open", "1 while the port is open, else 0.", G), |l| l.get(&l.port_open) as f64),
        per_line(lines, ("mbgate_line_outages", "Outages of the port: times it was lost (an adapter pulled out, a device server gone) or could not be opened at start, each once however many attempts it took to open it again (the reopenings: mbgate_line_opens_total).", C), |l| l.get(&l.outages) as f64),
        per_line(lines, ("mbgate_line_outage", "Time the port was not open after it was lost or could not be opened, the outage under way included.", C), |l| l.outage_time(now).as_secs_f64()).seconds(),
    ];
    let mut last = Family::new(
        "mbgate_line_last_reply_timestamp",
        "When the last reply came (Unix time); absent before the first.",
        G,
    )
    .seconds();
    let unix = SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .unwrap_or_default();
    for l in lines {
        if let Some(ago) = l.since_last_reply(now) {
            last.values
                .push((line_label(l), unix.saturating_sub(ago).as_secs_f64()));
        }
    }
    families.push(last);
    families.push(exceptions(lines));
    families.push(dropped_by_reason(lines));
    families
}

/// Bytes dropped by line and reason (docs/reliability.md "Knowing the wire"):
/// `too_early` (before the request could have left the wire), `echo` (a copy of the
/// request begun before it left), `stale` (there before the request was sent, or
/// answering none), `other` (garbage, failed checks, refuted and partial frames).
fn dropped_by_reason(lines: &[Arc<LineMetrics>]) -> Family {
    let mut f = Family::new(
        "mbgate_line_dropped_bytes_by_reason",
        "Bytes from the device discarded, by reason: too_early (before the request could have left the wire at baud_rate), echo (a copy of the request begun before it left), stale (there before the request was sent, or answering none), other (garbage, failed checks, refuted or partial frames).",
        C,
    );
    for l in lines {
        let st = &l.stats;
        let named = [
            ("too_early", st.get(&st.dropped_too_early)),
            ("echo", st.get(&st.dropped_echo)),
            ("stale", st.get(&st.dropped_stale)),
        ];
        let other = st
            .get(&st.dropped_bytes)
            .saturating_sub(named.iter().map(|(_, n)| n).sum());
        for (reason, n) in named.into_iter().chain([("other", other)]) {
            let labels = vec![("line", l.name.clone()), ("reason", reason.into())];
            f.values.push((labels, n as f64));
        }
    }
    f
}

/// Exception answers by line, source and code.
fn exceptions(lines: &[Arc<LineMetrics>]) -> Family {
    let mut f = Family::new(
        "mbgate_line_exceptions",
        "Exception replies to masters: source=device, sent by the device; source=gateway, made by mbgate (0x01 a read or another non-write to unit 0 on a bus, 0x0A no path, 0x06 queue full, 0x0B no reply in time or unit backed off).",
        C,
    );
    for l in lines {
        let st = &l.stats;
        let made = [
            (
                ExceptionCode::ILLEGAL_FUNCTION.get(),
                st.get(&st.broadcasts_refused),
            ),
            (ExceptionCode::SERVER_DEVICE_BUSY.get(), st.get(&st.busy)),
            (
                ExceptionCode::GATEWAY_PATH_UNAVAILABLE.get(),
                st.get(&st.unavailable),
            ),
            (
                ExceptionCode::GATEWAY_TARGET_FAILED.get(),
                st.get(&st.timeouts) + st.get(&st.backed_off),
            ),
        ];
        for (c, n) in made {
            let labels = vec![
                ("line", l.name.clone()),
                ("source", "gateway".into()),
                ("code", code(c)),
            ];
            f.values.push((labels, n as f64));
        }
        for (c, n) in l.device_exceptions() {
            let labels = vec![
                ("line", l.name.clone()),
                ("source", "device".into()),
                ("code", code(c)),
            ];
            f.values.push((labels, n as f64));
        }
    }
    f
}

fn unit_families(
    lines: &[Arc<LineMetrics>],
    now: Instant,
    e: &mut DescriptorEncoder,
) -> std::fmt::Result {
    type Get = fn(&super::UnitMetrics) -> &std::sync::atomic::AtomicU64;
    let plain: [(&str, &str, MetricType, Get); 4] = [
        ("mbgate_unit_requests", "Requests for the unit.", C, |u| {
            &u.requests
        }),
        (
            "mbgate_unit_replies",
            "Replies from the unit delivered to masters.",
            C,
            |u| &u.replies,
        ),
        (
            "mbgate_unit_timeouts",
            "Attempts the unit did not answer in time.",
            C,
            |u| &u.timeouts,
        ),
        (
            "mbgate_unit_backed_off",
            "1 from when the unit is backed off (RTU/ASCII) until it answers again, else 0.",
            G,
            |u| &u.backed_off,
        ),
    ];
    for (name, help, kind, get) in plain {
        let mut f = Family::new(name, help, kind);
        for l in lines {
            for (unit, u) in l.units() {
                let labels = vec![("line", l.name.clone()), ("unit", unit.to_string())];
                f.values.push((labels, l.get(get(u)) as f64));
            }
        }
        f.encode(e)?;
    }
    unit_state_families(lines, now, e)?;
    unit_reply_histogram(lines, e)
}

/// Whether each unit answers, and its learned response timeout.
fn unit_state_families(
    lines: &[Arc<LineMetrics>],
    now: Instant,
    e: &mut DescriptorEncoder,
) -> std::fmt::Result {
    let mut f = Family::new(
        "mbgate_unit_not_answering",
        "1 from the unit's third timeout in a row until it answers again, or until a minute passes without a timeout (nobody asks it), else 0.",
        G,
    );
    for l in lines {
        for (unit, u) in l.units() {
            let labels = vec![("line", l.name.clone()), ("unit", unit.to_string())];
            f.values
                .push((labels, f64::from(u8::from(l.not_answering(u, now)))));
        }
    }
    f.encode(e)?;
    let mut f = Family::new(
        "mbgate_unit_response_timeout",
        "The unit's learned response timeout (response_timeout_ms = \"auto\"), why: start or timeout (at the ceiling), learned (p99 of its replies x 2), floor, ceiling.",
        G,
    )
    .seconds();
    for l in lines {
        for (unit, u) in l.units() {
            if let Some((t, why)) = u.learned() {
                let labels = vec![
                    ("line", l.name.clone()),
                    ("unit", unit.to_string()),
                    ("why", why.to_owned()),
                ];
                f.values.push((labels, t.as_secs_f64()));
            }
        }
    }
    f.encode(e)?;
    Ok(())
}

/// Each unit's reply times, a histogram.
fn unit_reply_histogram(lines: &[Arc<LineMetrics>], e: &mut DescriptorEncoder) -> std::fmt::Result {
    let mut m = e.encode_descriptor(
        "mbgate_unit_reply",
        "Reply time, from the request leaving for the device to its reply confirmed.",
        Some(&Unit::Seconds),
        MetricType::Histogram,
    )?;
    for l in lines {
        for (unit, u) in l.units() {
            let labels = vec![("line", l.name.clone()), ("unit", unit.to_string())];
            let (sum, count, buckets) = u.histogram();
            let fam = m.encode_family(&labels)?;
            let mut fam = fam;
            fam.encode_histogram::<Labels>(sum, count, &buckets, None)?;
        }
    }
    Ok(())
}

fn listener_families(listeners: &[(Arc<ListenerMetrics>, ListenerTransport)]) -> Vec<Family> {
    let per = |(name, help, kind): (&'static str, &'static str, MetricType),
               get: &dyn Fn(&ListenerMetrics) -> u64| {
        let mut f = Family::new(name, help, kind);
        f.values = listeners
            .iter()
            .map(|(l, t)| {
                let labels = vec![
                    ("listener", l.name.clone()),
                    ("transport", t.label().into()),
                ];
                (labels, get(l) as f64)
            })
            .collect();
        f
    };
    vec![
        per(("mbgate_listener_masters", "Masters connected now.", G), &|l| l.connected()),
        per(("mbgate_listener_connections", "Connections accepted.", C), &|l| l.stats.get(&l.stats.connections)),
        per(("mbgate_listener_refused_connections", "Connections closed at once: max_connections reached (on TLS, once authenticated).", C), &|l| l.stats.get(&l.stats.connections_refused)),
        per(("mbgate_listener_protocol_violations", "Connections closed for a frame that broke the MBAP rules.", C), &|l| l.stats.get(&l.stats.protocol_violations)),
        per(("mbgate_listener_dial_answers", "Answers of a dialed server to mbgate's identity or heartbeat (bytes that are no request, one each at most): dropped, never relayed.", C), &|l| l.stats.get(&l.stats.dial_answers)),
        per(("mbgate_listener_dropped_datagrams", "UDP datagrams dropped: not exactly one MBAP request, or beyond their source's share.", C), &|l| l.stats.get(&l.stats.datagrams_dropped)),
        per(("mbgate_listener_not_requests", "Frames from masters that are no request but an answer (an exception, a reply's shape, or on UDP the gateway's own reply sent back): dropped, never answered.", C), &|l| l.stats.get(&l.stats.not_requests)),
        per(("mbgate_listener_limited_exceptions", "Exception replies not sent to a UDP source past its budget of them.", C), &|l| l.stats.get(&l.stats.exceptions_limited)),
        per(("mbgate_listener_bad_requests", "Requests answered by mbgate with an exception: their PDU broke the protocol's limits.", C), &|l| l.stats.get(&l.stats.bad_requests)),
        per(("mbgate_listener_denied_connections", "Connections closed before any byte was read: the source is not in the listener's allow list.", C), &|l| l.stats.get(&l.stats.connections_denied)),
        per(("mbgate_listener_tls_failed", "TLS handshakes that failed, timed out or gave way to newer ones (no or a bad client certificate, an old protocol, the handshake budget full).", C), &|l| l.stats.get(&l.stats.tls_failed)),
        per(("mbgate_listener_tls_refused", "TLS masters refused for their role (none and no default_role, or one no [[role]] names).", C), &|l| l.stats.get(&l.stats.tls_refused)),
        per(("mbgate_listener_denied_requests", "Requests answered 0x01 because the listener's or the role's access rules do not permit them.", C), &|l| l.stats.get(&l.stats.denied)),
    ]
}

/// Each master connected now, with its listener, address, and on TLS its role and
/// certificate subject; the value is when it connected. At most `max_connections` a
/// listener; a series ends when its master leaves.
fn masters(all: &[super::MasterSeen]) -> Family {
    let mut f = Family::new(
        "mbgate_master_connected_timestamp",
        "A master connected now (Unix time it connected), by listener, peer, connection id, and on a TLS listener its role and certificate subject.",
        G,
    )
    .seconds();
    for m in all {
        let (role, subject) = m.tls.clone().unwrap_or_default();
        let labels = vec![
            ("listener", m.listener.clone()),
            ("conn", m.conn.to_string()),
            ("peer", m.peer.to_string()),
            ("role", role),
            ("subject", subject),
        ];
        f.values.push((labels, m.since));
    }
    f
}
